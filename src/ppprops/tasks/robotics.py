"""FetchReachDense-v4 (gymnasium-robotics): move the Fetch arm's gripper to a goal point.

The env observes a Dict: ``observation`` (10: gripper position 3, finger state 2, gripper linear
velocity 3, finger velocity 2), ``achieved_goal`` (3, the gripper position again) and ``desired_goal``
(3). The paper's policy sees n_s = 6 values: we keep the gripper position and the goal position.

Why these six: the action moves the gripper by a bounded displacement per step, so the ideal
controller is proportional to (goal - gripper). With both positions in s, that controller is exactly
linear (W = k[-I; I]), so the linear policy class contains it. The velocities add little because the
env commands positions, the finger state is irrelevant to reaching, and achieved_goal duplicates the
gripper position. Relative coordinates would also fit in 3 values, but raw positions keep s as the
env's own observation (no feature engineering) and fill the paper's n_s = 6.

There are no reward components: the dense reward is a single term (minus the distance to the goal).
Feedback is the episode length and whether the final step counts as a success (info ``is_success``).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import MissingExtraError
from .base import EpisodeFeedback, Task, TaskText

_TEXT = "ppprops.tasks.descriptions"
# gymnasium-robotics' FetchReach breaks at reset with mujoco >= 3.12 (an enum comparison changed).
MUJOCO_BELOW = (3, 12)


@dataclass(frozen=True)
class DictSlices:
    """Picks (key, indices) slices out of a Dict observation and concatenates them, in order."""

    names: tuple[str, ...]
    parts: tuple[tuple[str, tuple[int, ...]], ...]

    def __call__(self, obs: Any) -> NDArray[np.float64]:
        return np.concatenate([np.asarray(obs[key], dtype=np.float64).reshape(-1)[list(idx)] for key, idx in self.parts])


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(p) for p in text.split(".")[:2] if p.isdigit())


def setup_robotics() -> None:
    """Register gymnasium-robotics' envs; refuse a mujoco version that is known to break Fetch."""
    try:
        import gymnasium as gym
        import mujoco

        with contextlib.redirect_stderr(io.StringIO()):  # a notice about unrelated Adroit envs
            import gymnasium_robotics
    except ImportError as e:
        raise MissingExtraError("robotics", "FetchReachDense-v4") from e
    if _version(mujoco.__version__) >= MUJOCO_BELOW:
        raise MissingExtraError("robotics", f"FetchReachDense-v4 (mujoco < 3.12, found {mujoco.__version__})")
    gym.register_envs(gymnasium_robotics)


class FetchRecorder:
    """Episode length and whether the gripper ended within the success distance of the goal."""

    def __init__(self) -> None:
        self.success = 0.0

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        self.success = float(info.get("is_success", 0.0))

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        return EpisodeFeedback(components={}, diagnostics={"episode_length": float(steps), "success": self.success})


FETCH_REACH = Task(
    name="FetchReachDense",
    env_id="FetchReachDense-v4",
    n_s=6,
    n_a=4,
    action_type="continuous",
    observation=DictSlices(
        names=("gripper_x", "gripper_y", "gripper_z", "goal_x", "goal_y", "goal_z"),
        parts=(("observation", (0, 1, 2)), ("desired_goal", (0, 1, 2))),
    ),
    feedback=FetchRecorder,
    text=TaskText.load(_TEXT, "fetch_reach.toml"),
    diagnostics=("episode_length", "success"),
    # No optimum is known: each step pays minus the gripper-goal distance, so 0 bounds the return,
    # but the goal starts away from the gripper and the best reachable return depends on the goal
    # drawn. No preset states a target (the paper's best reported mean is about -0.51).
    optimal_return=None,
    setup=setup_robotics,
)

TASKS = (FETCH_REACH,)
