"""Client-side facts the hardened preset needs about a task, and the run's codec and secrets.

Tasks are plain data owned elsewhere; what matters for privacy (which diagnostics pin the
return or a reward component, the rough size of returns) is kept here, next to the codec.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..privacy.knowledge import facts_for
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

# Diagnostics that, with public knowledge of the task, determine the raw return or a raw reward
# component (docs/threat-model.md): the episode length is the CartPole return, the Acrobot return
# together with `success`, and the healthy/alive reward of the locomotion tasks (a constant per
# step); it also states the time limit. Every task reports it, so it is hidden for every task.
RETURN_DETERMINING: dict[str, frozenset[str]] = {"*": frozenset({"episode_length"})}

# Rough magnitude of a task's returns, for the secret reward origin s ~ U(-S, S). The optimal
# return is used when the task knows it; these cover the rest.
REWARD_SCALE: dict[str, float] = {"Acrobot": 500.0, "FetchReachDense": 50.0}
DEFAULT_REWARD_SCALE = 1000.0


# The reward component left out of the history when return-determining feedback is hidden: with it
# shown, the printed return equals the sum of the printed components once decoded, an equation per
# entry in the reward secrets (the additivity attack). The locomotion tasks leave out the survive
# term, which is also the one whose value is public (healthy reward x episode length, and exactly
# healthy reward x time limit at the time limit); other tasks their first component.
RESIDUAL_COMPONENT: dict[str, str] = {"Ant": "reward_survive", "Humanoid": "reward_survive"}


def return_determining(task_name: str) -> frozenset[str]:
    """Diagnostics that pin the raw return of ``task_name`` (hidden by ``hide_return_diagnostics``)."""
    return RETURN_DETERMINING["*"] | RETURN_DETERMINING.get(task_name, frozenset())


def residual_component(task: Task) -> frozenset[str]:
    """The component hidden with ``hide_return_diagnostics`` (none for tasks without components)."""
    if not task.components:
        return frozenset()
    family = task.name.split("-")[0]
    name = RESIDUAL_COMPONENT.get(family)
    return frozenset({name if name in task.components else task.components[0]})


def reward_scale(task: Task) -> float:
    """The public magnitude of the task's returns (reward units): |optimal return|, else a per-task constant.

    Bounds the secret reward offsets s and s_k of ``secret_offsets``.
    """
    if task.optimal_return is not None and task.optimal_return != 0:
        return abs(float(task.optimal_return))
    return REWARD_SCALE.get(task.name, DEFAULT_REWARD_SCALE)


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
        hidden_diagnostics=return_determining(task.name) if m.hide_return_diagnostics else frozenset(),
        hidden_components=residual_component(task) if m.hide_return_diagnostics else frozenset(),
        resolution=facts_for(task.name).resolution,
        episodes=config.episodes,
        reward_scale=reward_scale(task),
    )
