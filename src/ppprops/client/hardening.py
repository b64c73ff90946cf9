"""Client-side facts the hardened preset needs about a task, and the run's codec and secrets.

The facts live with each task (its task file's ``[privacy]`` table, ``tasks.facts.PrivacyFacts``,
completed for the task by ``privacy.knowledge.facts_for``, as the attacks read them): which
diagnostics pin the return, which reward component is left out, the public step of each reward
quantity and the rough size of returns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..privacy.knowledge import facts_for
from ..tasks.facts import DEFAULT_REWARD_SCALE
from .codec import Codec
from .mechanisms import Mechanisms
from .secrets import Secrets, os_rng

if TYPE_CHECKING:
    from ..tasks.base import Task


@dataclass(frozen=True)
class EncodingSettings:
    """The run settings the secrets and the codec depend on (``RunConfig.encoding`` makes them):
    the mechanisms, the public box of every raw parameter, and the episodes per candidate (a
    mean over them has a finer public resolution, which the hardened dither follows)."""

    mechanisms: Mechanisms
    box: tuple[float, float]
    episodes: int = 1
    grid: bool = False  # encoded parameters on the integer grid of a secret global factor (the grid number format)


def return_determining(task: Task) -> frozenset[str]:
    """Diagnostics that, with public knowledge of ``task``, pin its raw return or a raw component (hidden by
    ``hide_return_diagnostics``; docs/threat-model.md): the task's ``privacy.return_determining``, and
    ``episode_length`` for every task (the CartPole return, the Acrobot return with ``success``, the
    healthy reward of the locomotion tasks; it also states the time limit)."""
    return frozenset(facts_for(task).return_determining or ())


def anchoring(task: Task) -> frozenset[str]:
    """Diagnostics whose value marks an episode end at a public cap (hidden by ``hide_anchors``;
    docs/threat-model.md, "Anchored returns"): the diagnostic of each of the task's
    ``privacy.caps`` (CartPole ``termination``, whose ``time_limit`` pins the raw return to 500;
    Acrobot ``success``, whose 0 pins it to -500). The whole diagnostic goes, for every entry:
    leaving out only the marked value would mark the entry by its absence."""
    return frozenset(c.diagnostic for c in facts_for(task).caps or ())


def residual_component(task: Task) -> frozenset[str]:
    """The component hidden with ``hide_return_diagnostics`` (none for tasks without components).

    With every component shown, the printed return equals the sum of the printed components once
    decoded, an equation per entry in the reward secrets (the additivity attack): one is left out.
    The task's ``privacy.residual_component`` (the locomotion tasks: the survive term, whose value
    is public anyway), else its first component.
    """
    name = facts_for(task).residual_component
    if not task.components or not name:
        return frozenset()
    return frozenset({name if name in task.components else task.components[0]})


def reward_scale(task: Task) -> float:
    """The public magnitude of the task's returns (reward units): its ``privacy.reward_scale``, else
    |optimal return|, else 1000 (``tasks.facts.DEFAULT_REWARD_SCALE``).

    Bounds the secret reward offsets s and s_k of ``secret_offsets``.
    """
    return facts_for(task).reward_scale or DEFAULT_REWARD_SCALE


def generate_secrets(run_id: str, task: Task, config: EncodingSettings, rng: np.random.Generator | None = None) -> Secrets:
    """The one routine that draws a run's secrets: the paper's, plus what each hardening switch on needs.

    ``rng`` None draws from the OS entropy source (``ppprops run``); a grid passes a generator
    keyed by its master key and the run's name, so the same routine serves both. Draw order:
    paper runs a, c; hardened runs the hardened a, m, c, s, p and then, when parameters are not
    warped (a_j is then the paper's scale, not the warped coordinate's), the paper's a. Each
    switch keeps only the secret it needs (secret_offsets: m, s; warp_rewards: p).
    """
    m = config.mechanisms
    rng = os_rng() if rng is None else rng
    if not m.hardened:
        return Secrets.generate(run_id, task.D, rng=rng)
    h = Secrets.generate_hardened(run_id, task.D, box=config.box, reward_scale=reward_scale(task), rng=rng)
    a = h.a if m.warp_params else Secrets.generate(run_id, task.D, rng=rng).a
    return Secrets(
        run_id=run_id,
        a=a,
        c=h.c,
        m=h.m if m.secret_offsets else None,
        s=h.s if m.secret_offsets else None,
        p=h.p if m.warp_rewards else None,
    )


def codec_for(secrets: Secrets, task: Task, config: EncodingSettings) -> Codec:
    """The run's codec, with every mechanism of its configuration."""
    m = config.mechanisms
    return Codec(
        secrets,
        encode_params=m.encode_params,
        scale_rewards=m.scale_rewards,
        offsets=m.secret_offsets,
        warp_params=m.warp_params,
        warp_rewards=m.warp_rewards,
        box=config.box,
        hidden_diagnostics=(return_determining(task) if m.hide_return_diagnostics else frozenset())
        | (anchoring(task) if m.hide_anchors else frozenset()),
        hidden_components=residual_component(task) if m.hide_return_diagnostics else frozenset(),
        resolution=facts_for(task).resolution or {},
        episodes=config.episodes,
        reward_scale=reward_scale(task),
        grid=config.grid,
    )
