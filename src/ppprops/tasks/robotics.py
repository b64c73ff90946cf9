"""The setup check of the paper's FetchReachDense-v4 task (gymnasium-robotics; tasks/paper/fetch-reach-dense.toml).

The task: move the Fetch arm's gripper to a goal point.

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
Feedback is the episode length and whether the final step counts as a success (info ``is_success``,
declared as a diagnostic in the task file).
"""

from __future__ import annotations

import contextlib
import io

from ..errors import MissingExtraError

# gymnasium-robotics' FetchReach breaks at reset with mujoco >= 3.12 (an enum comparison changed).
MUJOCO_BELOW = (3, 12)


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
