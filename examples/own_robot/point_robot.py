"""A small custom robot for the "Bring your own robot" guide (docs/own-robot.md).

A point mass on a plane is pushed by two thrusters towards a goal. Its constructor needs an
argument (the mass, in kg) and it has no time limit of its own: the task file supplies both
(``env_kwargs`` and ``max_episode_steps``). Each step's ``info`` carries the two terms of the reward
and two diagnostics, which the task file declares as feedback.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

DT = 0.1  # seconds per step
FRICTION = 0.5  # velocity lost per second, as a fraction
EFFORT_COST = 0.05


class PointRobot(gym.Env):
    """Observation: x, y, vx, vy of the robot and the goal's gx, gy (m, m/s). Action: thrust in [-1, 1]^2 (N).

    Reward per step: minus the distance to the goal (m) minus 0.05 times the squared thrust; the
    episode ends when the robot is within ``goal_radius`` of the goal.
    """

    metadata = {"render_modes": []}

    def __init__(self, mass: float, goal_radius: float = 0.1) -> None:
        if mass <= 0:
            raise ValueError(f"mass must be positive, got {mass}")
        self.mass = float(mass)
        self.goal_radius = float(goal_radius)
        high = np.array([5.0, 5.0, 10.0, 10.0, 5.0, 5.0], dtype=np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._pos = np.zeros(2)
        self._vel = np.zeros(2)
        self._goal = np.zeros(2)

    def _obs(self) -> np.ndarray:
        return np.concatenate([self._pos, self._vel, self._goal]).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._pos = self.np_random.uniform(-2.0, 2.0, size=2)
        self._vel = np.zeros(2)
        self._goal = self.np_random.uniform(-2.0, 2.0, size=2)
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        force = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self._vel = (1.0 - FRICTION * DT) * self._vel + DT * force / self.mass
        self._pos = np.clip(self._pos + DT * self._vel, -5.0, 5.0)
        distance = float(np.linalg.norm(self._goal - self._pos))
        effort = float(EFFORT_COST * np.sum(force**2))
        reached = distance < self.goal_radius
        info = {"reward_distance": -distance, "reward_effort": -effort, "distance": distance, "reached": reached}
        return self._obs(), -distance - effort, reached, False, info


def make_point_robot(mass: float = 1.0, goal_radius: float = 0.1) -> gym.Env:
    """An env factory, as ``ppprops.search`` takes one: the robot with a 100-step time limit."""
    return gym.wrappers.TimeLimit(PointRobot(mass=mass, goal_radius=goal_radius), max_episode_steps=100)
