"""Feedback code of the paper's MuJoCo tasks: Ant-v5 and Humanoid-v5, each in three observation configurations.

The tasks are declared in tasks/paper/{ant,humanoid}-{torso,joints,ultra}.toml; this note explains them.

Torso is the env's observation with the extra terms switched off: the complete generalized position
(without the torso's x, y) and velocity. Ultra and Joints keep index subsets of it, so the three
configurations control the same robot and differ only in what the policy sees (Ultra < Joints < Torso).

Ant-v5 Torso (27): 0 torso z | 1-4 torso quaternion w,x,y,z | 5-12 joint angles hip_1, ankle_1, hip_2,
ankle_2, hip_3, ankle_3, hip_4, ankle_4 | 13-15 torso linear velocity x,y,z | 16-18 torso angular velocity
x,y,z | 19-26 the eight joint angular velocities, same joint order.

* Ant-Ultra (10) = torso height (0), forward velocity (13) and the eight leg joint angles (5-12): the
  height says how close the body is to the unhealthy range, the forward velocity is what the reward pays
  for, and the leg posture is the minimum a linear gait controller can feed back on.
* Ant-Joints (16) = Ultra + the torso tilt (quaternion x, y: about half the roll and pitch angles for
  small tilts; 2, 3) + the angular velocities of the four hips (19, 21, 23, 25). The hips swing the legs
  forward and back and so produce propulsion; their velocities give the controller damping and gait phase.
* Ant-Torso (27) = everything, adding heading (quaternion w, z), the other torso velocities and the
  ankle velocities.

Humanoid-v5 Torso (45): 0 torso z | 1-4 torso quaternion | 5-21 joint angles abdomen_z, abdomen_y,
abdomen_x, right_hip_x, right_hip_z, right_hip_y, right_knee, left_hip_x, left_hip_z, left_hip_y,
left_knee, right_shoulder1, right_shoulder2, right_elbow, left_shoulder1, left_shoulder2, left_elbow |
22-24 torso linear velocity | 25-27 torso angular velocity | 28-44 the 17 joint velocities, same order.

* Humanoid-Ultra (11) = torso height (0), torso tilt (quaternion x, y; 2, 3), forward velocity (22),
  roll and pitch rates (25, 26), and the sagittal joints that carry a walk: trunk pitch abdomen_y (6),
  hip flexion right/left_hip_y (10, 14) and knees (11, 15). A humanoid falls within tens of steps, so
  balance (height, tilt and its rate) comes first.
* Humanoid-Joints (26) = Ultra + the complete state of both legs (the hip_x/hip_z angles 8, 9, 12, 13
  and all eight leg joint velocities 31-38) + lateral trunk bending abdomen_x (7) with its velocity (30)
  and the abdomen_y velocity (29).
* Humanoid-Torso (45) = everything, adding heading, vertical/lateral velocity, yaw rate, trunk twist and
  the six arm joints.

Reward components are the env's own per-step terms (info ``reward_forward``, ``reward_survive``,
``reward_ctrl``, ``reward_contact``) summed over the episode; they add up to the return.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from numpy.typing import NDArray

from ..errors import MissingExtraError
from .base import EpisodeFeedback

COMPONENTS = ("reward_forward", "reward_survive", "reward_ctrl", "reward_contact")
DIAGNOSTICS = ("episode_length", "termination")

def require_mujoco() -> None:
    """Fail with the pip extra to install, not with Gymnasium's generic dependency error."""
    try:
        import mujoco  # noqa: F401
    except ImportError as e:
        raise MissingExtraError("mujoco", "each MuJoCo task (Ant-v5, Humanoid-v5)") from e


class LocomotionRecorder:
    """Sums the four reward terms; notes whether the robot became unhealthy or ran out of time."""

    def __init__(self) -> None:
        self.sums = dict.fromkeys(COMPONENTS, 0.0)

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        """Add the step's four reward terms from ``info``."""
        for k in COMPONENTS:
            self.sums[k] += float(info[k])

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        """Summed reward terms; episode length and why it ended (unhealthy or time limit)."""
        cause = "unhealthy" if terminated else "time_limit" if truncated else "stopped"
        return EpisodeFeedback(components=dict(self.sums), diagnostics={"episode_length": float(steps), "termination": cause})
