"""MuJoCo locomotion tasks of the paper: Ant-v5 and Humanoid-v5, each in three observation configurations.

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

import tomllib
from collections.abc import Mapping
from importlib import resources
from typing import Any

from numpy.typing import NDArray

from ..errors import MissingExtraError
from .base import EpisodeFeedback, FlatBox, Task, TaskText

_TEXT = "ppprops.tasks.descriptions"
COMPONENTS = ("reward_forward", "reward_survive", "reward_ctrl", "reward_contact")
DIAGNOSTICS = ("episode_length", "termination")

_ANT_LEGS = ("hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3", "hip_4", "ankle_4")
ANT_STATES = (
    ("torso_z", "torso_qw", "torso_qx", "torso_qy", "torso_qz")
    + _ANT_LEGS
    + ("torso_vx", "torso_vy", "torso_vz", "torso_wx", "torso_wy", "torso_wz")
    + tuple(f"{j}_vel" for j in _ANT_LEGS)
)
_HUMANOID_JOINTS = (
    "abdomen_z", "abdomen_y", "abdomen_x",
    "right_hip_x", "right_hip_z", "right_hip_y", "right_knee",
    "left_hip_x", "left_hip_z", "left_hip_y", "left_knee",
    "right_shoulder1", "right_shoulder2", "right_elbow",
    "left_shoulder1", "left_shoulder2", "left_elbow",
)  # fmt: skip
HUMANOID_STATES = (
    ("torso_z", "torso_qw", "torso_qx", "torso_qy", "torso_qz")
    + _HUMANOID_JOINTS
    + ("torso_vx", "torso_vy", "torso_vz", "torso_wx", "torso_wy", "torso_wz")
    + tuple(f"{j}_vel" for j in _HUMANOID_JOINTS)
)

ANT_ULTRA = (0, 5, 6, 7, 8, 9, 10, 11, 12, 13)
ANT_JOINTS = tuple(sorted(ANT_ULTRA + (2, 3, 19, 21, 23, 25)))
HUMANOID_ULTRA = (0, 2, 3, 6, 10, 11, 14, 15, 22, 25, 26)
HUMANOID_JOINTS = tuple(sorted(HUMANOID_ULTRA + (7, 8, 9, 12, 13, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38)))

ANT_KWARGS: Mapping[str, Any] = {"include_cfrc_ext_in_observation": False}
HUMANOID_KWARGS: Mapping[str, Any] = {
    "include_cinert_in_observation": False,
    "include_cvel_in_observation": False,
    "include_qfrc_actuator_in_observation": False,
    "include_cfrc_ext_in_observation": False,
}


def require_mujoco() -> None:
    """Fail with the pip extra to install, not with Gymnasium's generic dependency error."""
    try:
        import mujoco  # noqa: F401
    except ImportError as e:
        raise MissingExtraError("mujoco", "the MuJoCo tasks (Ant-v5, Humanoid-v5)") from e


class LocomotionRecorder:
    """Sums the four reward terms; notes whether the robot became unhealthy or ran out of time."""

    def __init__(self) -> None:
        self.sums = dict.fromkeys(COMPONENTS, 0.0)

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        for k in COMPONENTS:
            self.sums[k] += float(info[k])

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        cause = "unhealthy" if terminated else "time_limit" if truncated else "stopped"
        return EpisodeFeedback(components=dict(self.sums), diagnostics={"episode_length": float(steps), "termination": cause})


def text_for_states(filename: str, names: tuple[str, ...]) -> TaskText:
    """A TaskText whose observation lines are looked up by state name in the file's [states] table.

    One file per robot describes every state once; each configuration picks its lines by name, so
    the three configurations can never describe the same index differently.
    """
    raw = tomllib.loads(resources.files(_TEXT).joinpath(filename).read_text(encoding="utf-8"))
    states: Mapping[str, str] = raw["states"]
    missing = [n for n in names if n not in states]
    if missing:
        raise ValueError(f"{filename}: no description for state(s) {', '.join(missing)}")
    return TaskText(
        summary=raw["summary"].strip(),
        observations=tuple(states[n] for n in names),
        actions=tuple(raw["actions"]),
        reward_structure=raw["reward_structure"].strip(),
        reward_hint=raw["reward_hint"].strip(),
        hints=raw.get("hints", "").strip(),
        components=dict(raw.get("components", {})),
        diagnostics=dict(raw.get("diagnostics", {})),
    )


def _task(name: str, env_id: str, all_names: tuple[str, ...], indices: tuple[int, ...] | None, n_a: int,
          text_file: str, kwargs: Mapping[str, Any]) -> Task:  # fmt: skip
    names = all_names if indices is None else tuple(all_names[i] for i in indices)
    return Task(
        name=name,
        env_id=env_id,
        n_s=len(names),
        n_a=n_a,
        action_type="continuous",
        observation=FlatBox(names=names, indices=indices),
        feedback=LocomotionRecorder,
        text=text_for_states(text_file, names),
        components=COMPONENTS,
        diagnostics=DIAGNOSTICS,
        env_kwargs=dict(kwargs),
        # Forward progress is not bounded by anything the task states, so no return is defensible
        # as "the optimum"; the prompt then simply states none.
        optimal_return=None,
        setup=require_mujoco,
    )


TASKS = (
    _task("Ant-Ultra", "Ant-v5", ANT_STATES, ANT_ULTRA, 8, "ant.toml", ANT_KWARGS),
    _task("Ant-Joints", "Ant-v5", ANT_STATES, ANT_JOINTS, 8, "ant.toml", ANT_KWARGS),
    _task("Ant-Torso", "Ant-v5", ANT_STATES, None, 8, "ant.toml", ANT_KWARGS),
    _task("Humanoid-Ultra", "Humanoid-v5", HUMANOID_STATES, HUMANOID_ULTRA, 17, "humanoid.toml", HUMANOID_KWARGS),
    _task("Humanoid-Joints", "Humanoid-v5", HUMANOID_STATES, HUMANOID_JOINTS, 17, "humanoid.toml", HUMANOID_KWARGS),
    _task("Humanoid-Torso", "Humanoid-v5", HUMANOID_STATES, None, 17, "humanoid.toml", HUMANOID_KWARGS),
)
