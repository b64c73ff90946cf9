"""What a curious provider may know about a task without any secret (docs/threat-model.md).

The task itself, its public feasible box, the environment's reward structure and time limit,
and the warm-up procedure are public. The facts the attacks use live with each task, in its task
file's ``[privacy]`` table (``ppprops.tasks.facts.PrivacyFacts``): ``facts_for(task)`` completes
them for the task and lists the facts it leaves unknown, so an attack that needs one can say why
it did not run (``PrivacyFacts.not_run``) instead of running on an invented default.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..tasks.facts import ALWAYS_HIDDEN, DEFAULT_REWARD_SCALE, PrivacyFacts

if TYPE_CHECKING:
    from ..tasks.base import Task
    from ..tasks.spec import TaskSpec

__all__ = ["ALWAYS_HIDDEN", "DEFAULT_REWARD_SCALE", "facts_for", "not_run_lines"]


def facts_for(task: Task | TaskSpec | str) -> PrivacyFacts:
    """The privacy facts of ``task`` completed for it (``PrivacyFacts.completed``): a Task or TaskSpec
    is read from its declaration.

    A string is the name of a task registered in this process (the paper's tasks always are);
    any other name gets no facts, every one unknown. Prefer passing the Task: a user's task is
    found by name only when it was registered.
    """
    from ..tasks import Task, privacy_facts, registered

    if isinstance(task, str):
        found = registered(task)
        if found is None:
            none = PrivacyFacts()
            return none.completed(task, (), optimal_return=None, public_env=False, unknown=none.unknown)
        task = found
    spec = task.spec if isinstance(task, Task) else task
    components = tuple(task.components) if isinstance(task, Task) else tuple(c.name for c in task.components)
    public = spec.public_env() if spec is not None else False
    return privacy_facts(task).completed(task.name, components, optimal_return=task.optimal_return, public_env=public)


def not_run_lines(facts: PrivacyFacts, needs: Sequence[tuple[str, Sequence[str]]]) -> list[str]:
    """``not_run`` for each (attack, facts it needs), the lines of those that cannot run."""
    return [line for attack, names in needs if (line := facts.not_run(attack, *names)) is not None]
