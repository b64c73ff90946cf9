"""Classic-control tasks of the paper: CartPole-v1 and Acrobot-v1."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from numpy.typing import NDArray

from .base import EpisodeFeedback, FlatBox, Task, TaskText

_TEXT = "ppprops.tasks.descriptions"


class _CartPoleRecorder:
    """Episode length and why the episode ended (the pole fell, the cart left the track, or time ran out)."""

    def __init__(self) -> None:
        self.last_obs: NDArray[Any] | None = None

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        self.last_obs = obs

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        if terminated and self.last_obs is not None:
            x, _, angle, _ = (float(v) for v in self.last_obs)
            cause = "cart_out_of_bounds" if abs(x) > 2.4 else "pole_fell"
        elif truncated:
            cause = "time_limit"
        else:
            cause = "stopped"
        return EpisodeFeedback(components={}, diagnostics={"episode_length": float(steps), "termination": cause})


class _AcrobotRecorder:
    """Episode length, whether the tip reached the goal height, and the mean height of the free tip."""

    def __init__(self) -> None:
        self.height_sum = 0.0
        self.n = 0

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        c1, s1, c2, s2 = (float(v) for v in obs[:4])
        # tip height relative to the pivot, in link lengths: -cos(t1) - cos(t1 + t2)
        self.height_sum += -c1 - (c1 * c2 - s1 * s2)
        self.n += 1

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        mean_h = self.height_sum / self.n if self.n else 0.0
        return EpisodeFeedback(
            components={},
            diagnostics={"episode_length": float(steps), "success": 1.0 if terminated else 0.0, "mean_tip_height": mean_h},
        )


CARTPOLE = Task(
    name="CartPole",
    env_id="CartPole-v1",
    n_s=4,
    n_a=2,
    action_type="discrete",
    observation=FlatBox(names=("cart_position", "cart_velocity", "pole_angle", "pole_angular_velocity")),
    feedback=_CartPoleRecorder,
    text=TaskText.load(_TEXT, "cartpole.toml"),
    diagnostics=("episode_length", "termination"),
    optimal_return=500.0,
)

ACROBOT = Task(
    name="Acrobot",
    env_id="Acrobot-v1",
    n_s=6,
    n_a=3,
    action_type="discrete",
    observation=FlatBox(names=("cos_theta1", "sin_theta1", "cos_theta2", "sin_theta2", "theta1_dot", "theta2_dot")),
    feedback=_AcrobotRecorder,
    text=TaskText.load(_TEXT, "acrobot.toml"),
    diagnostics=("episode_length", "success", "mean_tip_height"),
    # No optimum is known: every step costs -1 until the swing-up, and the fastest possible
    # swing-up is not known in closed form (0 bounds it but is unreachable). So no preset
    # states a target here; the paper's best reported mean is about -71.6.
    optimal_return=None,
)

TASKS = (CARTPOLE, ACROBOT)
