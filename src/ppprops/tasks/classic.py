"""Feedback code of the paper's classic-control tasks (CartPole-v1, Acrobot-v1; declared in tasks/paper/*.toml)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from numpy.typing import NDArray

from .base import EpisodeFeedback


class CartPoleRecorder:
    """Episode length and why the episode ended (the pole fell, the cart left the track, or time ran out)."""

    def __init__(self) -> None:
        self.last_obs: NDArray[Any] | None = None

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        """Keep the observation (the last one tells why the episode ended)."""
        self.last_obs = obs

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        """Episode length and why it ended (pole fell, cart left the track, time limit)."""
        if terminated and self.last_obs is not None:
            x, _, angle, _ = (float(v) for v in self.last_obs)
            cause = "cart_out_of_bounds" if abs(x) > 2.4 else "pole_fell"
        elif truncated:
            cause = "time_limit"
        else:
            cause = "stopped"
        return EpisodeFeedback(components={}, diagnostics={"episode_length": float(steps), "termination": cause})


class AcrobotRecorder:
    """Episode length, whether the tip reached the goal height, and the mean height of the free tip."""

    def __init__(self) -> None:
        self.height_sum = 0.0
        self.n = 0

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        """Track the free tip's height."""
        c1, s1, c2, s2 = (float(v) for v in obs[:4])
        # tip height relative to the pivot, in link lengths: -cos(t1) - cos(t1 + t2)
        self.height_sum += -c1 - (c1 * c2 - s1 * s2)
        self.n += 1

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        """Episode length, whether the tip reached the goal height, and its mean height."""
        mean_h = self.height_sum / self.n if self.n else 0.0
        return EpisodeFeedback(
            components={},
            diagnostics={"episode_length": float(steps), "success": 1.0 if terminated else 0.0, "mean_tip_height": mean_h},
        )
