"""What a curious provider may know about a task without any secret (docs/threat-model.md).

The task itself, its public feasible box, the environment's reward structure and time limit,
and the warm-up procedure are public. The facts the attacks use live with each task, in its task
file's ``[privacy]`` table (``ppprops.tasks.facts``; issue 20): ``facts_for(task)`` reads them into
``PublicFacts`` and lists the facts the task leaves unknown, so an attack that needs one can say
why it did not run (``PublicFacts.not_run``) instead of running on an invented default.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ..tasks.facts import Cap

if TYPE_CHECKING:
    from ..tasks.base import Task
    from ..tasks.spec import TaskSpec

ALWAYS_HIDDEN = frozenset({"episode_length"})  # pp-hardened hides it for every task (it states the time limit)
DEFAULT_REWARD_SCALE = 1000.0  # the bound of the secret offsets when a task states no scale (then listed as unknown)


@dataclass(frozen=True)
class PublicFacts:
    """Public facts about a task's returns and reward components (its ``[privacy]`` table; ``tasks.facts``).

    A fact the task does not declare keeps the neutral value below (False, empty, None) and is
    named in ``unknown``; a fact declared ``false`` ("the task has none") keeps the same value and
    is not. Attacks and the audit read ``unknown`` through ``missing`` / ``not_run``.
    """

    task: str
    integer_returns: bool = False  # every per-step reward is an integer (a lattice of returns)
    # raw return = sum(coef * diagnostic) + const, from the environment's definition
    return_formula: dict[str, float] = field(default_factory=dict)
    formula_const: float = 0.0
    # returns a time limit pins: (side, value, diagnostic that marks it, value of that diagnostic)
    caps: tuple[Cap, ...] = ()
    # public range of one episode's return (for the warped-lattice search), None if unbounded or unknown
    return_range: tuple[float, float] | None = None
    # public step of each reward quantity in one episode ("return" or a component name): values
    # are whole multiples of it. The hardened codec dithers these by a secret amount below one step.
    resolution: dict[str, float] = field(default_factory=dict)
    # locomotion: the survive component is healthy_reward per step; a saturated controller costs
    # exactly ctrl_per_step per step (ctrl_cost_weight * n_a * bound^2); episodes end at time_limit
    survive: str | None = None
    healthy_reward: float | None = None
    ctrl: str | None = None
    ctrl_per_step: float | None = None
    time_limit: int | None = None
    components: tuple[str, ...] = ()  # every reward component of the task (the ones that add up to the return)
    components_sum_to_return: bool = False
    public_env: bool = False  # an attacker can build and simulate the env (``TaskSpec.public_env``)
    return_determining: frozenset[str] = ALWAYS_HIDDEN  # diagnostics pp-hardened hides (episode_length always)
    residual_component: str | None = None  # the component pp-hardened leaves out; None: the task has none, or unknown
    reward_scale: float = DEFAULT_REWARD_SCALE  # public magnitude of returns: bound of the secret offsets
    unknown: tuple[str, ...] = ()  # facts the task does not declare (``tasks.facts.FACT_NAMES``)

    def missing(self, *facts: str) -> tuple[str, ...]:
        """Those of ``facts`` (names from ``tasks.facts.FACT_NAMES``) that the task leaves unknown."""
        return tuple(f for f in facts if f in self.unknown)

    def not_run(self, attack: str, *facts: str) -> str | None:
        """The line the audit prints when ``attack`` needs a fact the task leaves unknown, else None.

        ``attack X not run: fact Y unknown for task Z`` (every unknown fact named, comma-separated),
        e.g. ``facts.not_run("survive-length", "survive_component", "time_limit")``.
        """
        gone = self.missing(*facts)
        if not gone:
            return None
        return f"attack {attack} not run: fact{'s' if len(gone) > 1 else ''} {', '.join(gone)} unknown for task {self.task}"


def facts_for(task: Task | TaskSpec | str) -> PublicFacts:
    """The public facts of ``task`` (a Task or TaskSpec: read from its declaration; issue 20).

    A string is the name of a task registered in this process (the paper's tasks always are);
    any other name gets no facts, every one unknown. Prefer passing the Task: a user's task is
    found by name only when it was registered.

    Facts the task leaves unknown take neutral values (``PublicFacts``) and are listed in
    ``unknown``, except where pp-hardened needs a value: ``return_determining`` always holds
    ``episode_length``, ``residual_component`` falls back to the task's first component (one must
    be left out to close the additivity attack), and ``reward_scale`` to |optimal return|, else
    ``DEFAULT_REWARD_SCALE``; those fallbacks are still listed as unknown.
    """
    from ..tasks import Task, privacy_facts, registered
    from ..tasks.facts import PrivacyFacts

    if isinstance(task, str):
        found = registered(task)
        if found is None:
            return PublicFacts(task, unknown=PrivacyFacts().unknown())
        task = found
    name = task.name
    spec = task.spec if isinstance(task, Task) else task
    components = tuple(task.components) if isinstance(task, Task) else tuple(c.name for c in task.components)
    optimal = task.optimal_return
    p = privacy_facts(task)
    public = spec.public_env() if spec is not None else False
    formula = dict(p.return_formula) if p.return_formula else {}
    residual = p.residual_component if p.residual_component is not None else (components[0] if components else False)
    if p.reward_scale is not None:
        scale = float(p.reward_scale)
    elif optimal is not None and optimal != 0:
        scale = abs(float(optimal))
    else:
        scale = DEFAULT_REWARD_SCALE
    unknown = tuple(f for f in p.unknown() if not (f == "reward_scale" and optimal)  # |optimal return| states it
                    and not (f == "residual_component" and not components))  # fmt: skip
    return PublicFacts(
        task=name,
        integer_returns=bool(p.integer_returns),
        return_formula=formula,
        formula_const=float(p.return_formula_constant or 0.0),
        caps=tuple(p.caps or ()),
        return_range=p.return_range or None,
        resolution=dict(p.resolution or {}),
        survive=p.survive_component or None,
        healthy_reward=p.healthy_reward,
        ctrl=p.ctrl_component or None,
        ctrl_per_step=p.ctrl_per_step,
        time_limit=p.time_limit or None,
        components=components if p.components_sum_to_return else (),
        components_sum_to_return=bool(p.components_sum_to_return),
        public_env=public,
        return_determining=ALWAYS_HIDDEN | frozenset(p.return_determining or ()),
        residual_component=residual or None,
        reward_scale=scale,
        unknown=unknown,
    )


def not_run_lines(facts: PublicFacts, needs: Sequence[tuple[str, Sequence[str]]]) -> list[str]:
    """``not_run`` for each (attack, facts it needs), the lines of those that cannot run."""
    return [line for attack, names in needs if (line := facts.not_run(attack, *names)) is not None]
