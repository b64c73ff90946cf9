"""Feedback code of the paper's highway-v0 tasks (highway-env; declared in tasks/paper/highway*.toml).

The task: drive fast on the right of a busy four-lane highway without crashing.

Observation: Kinematics of 3 vehicles (the ego car and the two nearest cars ahead) x 5 features
(presence, x, y, vx, vy), flattened to 15 values; the other cars are relative to the ego car and every
feature is normalized and clipped to [-1, 1] by the env. Actions: Discrete(5) meta-actions.

Configuration (both tasks): highway-v0's defaults plus ``policy_frequency=5``. The default decides
once per simulated second, so a 40 s episode has only 40 steps and a return of at most 40, far below the
~150 the paper reports. Deciding five times a second gives 200 steps of the same 40 s drive and returns
up to 200, the paper's scale: holding the start lane at the start speed scores about 150-165 when it
does not crash. The simulation cost per episode is unchanged (600 frames at 15 Hz), about 45 ms a step
here. The reward weights are written out explicitly so the components below stay correct if the
package's defaults move.

``Highway-Fast`` is the same task with ``simulation_frequency=5`` (one frame per decision) and 20
instead of 50 other cars: about 8 ms a step, 1.5 s an episode, for quick experiments. Its returns are
on the same scale but not comparable to Highway's (coarser dynamics, lighter traffic).

Reward components. highway-env pays, per step,
    r = on_road * lmap(w_c*collision + w_r*right_lane + w_s*high_speed, [w_c, w_r + w_s], [0, 1])
      = on_road * (w_c*collision + w_r*right_lane + w_s*high_speed - w_c) / (w_r + w_s - w_c)
with the raw terms of info["rewards"]. We split it into four additive parts that sum to r exactly:
collision, right-lane and high-speed each get on_road * w_k * term / span, and the on-road part is the
normalization offset on_road * (-w_c) / span (2/3 per step with the default weights): the reward for
simply being on the road. The episodic sums of these four are the components; they add up to the return.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from numpy.typing import NDArray

from ..errors import MissingExtraError
from .base import EpisodeFeedback

COMPONENTS = ("high_speed_reward", "right_lane_reward", "collision_reward", "on_road_reward")
DIAGNOSTICS = ("episode_length", "crashed", "mean_speed")

# The reward weights of both task files (env_kwargs.config); a test checks they agree.
REWARD_CONFIG: Mapping[str, Any] = {
    "collision_reward": -1.0,
    "right_lane_reward": 0.1,
    "high_speed_reward": 0.4,
    "lane_change_reward": 0.0,
    "reward_speed_range": [20, 30],
    "normalize_reward": True,
}
def setup_highway() -> None:
    """Import highway-env (registers its ids); MissingExtraError naming the ``highway`` extra when it is absent."""
    try:
        import gymnasium as gym
        import highway_env
    except ImportError as e:
        raise MissingExtraError("highway", "each Highway task (highway-v0)") from e
    gym.register_envs(highway_env)


def split_reward(terms: Mapping[str, float], config: Mapping[str, Any] = REWARD_CONFIG) -> dict[str, float]:
    """One step's reward as four additive parts (see the module docstring); they sum to the env's reward."""
    w_c, w_r, w_s = (float(config[k]) for k in ("collision_reward", "right_lane_reward", "high_speed_reward"))
    on_road = float(terms["on_road_reward"])
    parts = {
        "high_speed_reward": w_s * float(terms["high_speed_reward"]),
        "right_lane_reward": w_r * float(terms["right_lane_reward"]),
        "collision_reward": w_c * float(terms["collision_reward"]),
        "on_road_reward": 0.0,
    }
    if config["normalize_reward"]:
        span = w_r + w_s - w_c
        parts = {k: v / span for k, v in parts.items()}
        parts["on_road_reward"] = -w_c / span
    return {k: on_road * v for k, v in parts.items()}


class HighwayRecorder:
    """Sums the four reward parts; reports the episode length, whether the ego car crashed, its mean speed."""

    def __init__(self) -> None:
        self.sums = dict.fromkeys(COMPONENTS, 0.0)
        self.speed_sum = 0.0
        self.n = 0
        self.crashed = 0.0

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        """Add the step's reward terms (info["rewards"]), speed and crash flag."""
        for k, v in split_reward(info["rewards"]).items():
            self.sums[k] += v
        self.speed_sum += float(info["speed"])
        self.n += 1
        self.crashed = float(bool(info["crashed"]))

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        """Summed reward terms; episode length, crash flag and mean speed as diagnostics."""
        diagnostics: dict[str, float | str] = {
            "episode_length": float(steps),
            "crashed": self.crashed,
            "mean_speed": self.speed_sum / self.n if self.n else 0.0,
        }
        return EpisodeFeedback(components=dict(self.sums), diagnostics=diagnostics)
