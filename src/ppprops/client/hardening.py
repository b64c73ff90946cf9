"""Client-side facts the hardened preset needs about a task, and the run's codec and secrets.

Tasks are plain data owned elsewhere; what matters for privacy (which diagnostics pin the
return or a reward component, the rough size of returns) is kept here, next to the codec.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .codec import Codec
from .secrets import Secrets

if TYPE_CHECKING:
    from ..config import RunConfig
    from ..tasks.base import Task

# Diagnostics that, with public knowledge of the task, determine the raw return or a raw reward
# component (docs/threat-model.md): the episode length is the CartPole return, the Acrobot return
# together with `success`, and the healthy/alive reward of the locomotion tasks (a constant per
# step); it also states the time limit. Every task reports it, so it is hidden for every task.
RETURN_DETERMINING: dict[str, frozenset[str]] = {"*": frozenset({"episode_length"})}

# Rough magnitude of a task's returns, for the secret reward origin s ~ U(-S, S). The optimal
# return is used when the task knows it; these cover the rest.
REWARD_SCALE: dict[str, float] = {"Acrobot": 500.0, "FetchReachDense": 50.0}
DEFAULT_REWARD_SCALE = 1000.0


def return_determining(task_name: str) -> frozenset[str]:
    return RETURN_DETERMINING["*"] | RETURN_DETERMINING.get(task_name, frozenset())


def reward_scale(task: Task) -> float:
    if task.optimal_return is not None and task.optimal_return != 0:
        return abs(float(task.optimal_return))
    return REWARD_SCALE.get(task.name, DEFAULT_REWARD_SCALE)


def generate_secrets(run_id: str, task: Task, config: RunConfig) -> Secrets:
    """The paper's secrets, plus what each hardening switch that is on needs (and nothing more).

    The hardened range of a_j is used only with warped parameters, where a_j is the warped
    coordinate's scale; otherwise a_j keeps the paper's distribution.
    """
    m = config.mechanisms
    paper = Secrets.generate(run_id, task.D)
    if not m.hardened:
        return paper
    h = Secrets.generate_hardened(run_id, task.D, box=config.box, reward_scale=reward_scale(task))
    return Secrets(
        run_id=run_id,
        a=h.a if m.warp_params else paper.a,
        c=paper.c,
        m=h.m if m.secret_offsets else None,
        s=h.s if m.secret_offsets else None,
        p=h.p if m.warp_rewards else None,
    )


def codec_for(secrets: Secrets, task: Task, config: RunConfig) -> Codec:
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
    )
