"""Recording one episode as a state -> action sequence (R2PO's trajectory evidence).

Episodes are seeded, so re-running the median episode of an evaluation reproduces it exactly
without storing every trajectory of every evaluation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .evaluation import make_policy
from .tasks.base import Task


def record_rollout(task: Task, env: Any, theta: np.ndarray, seed: int) -> tuple[float, list[tuple[tuple[float, ...], str]]]:
    policy = make_policy(task, theta, env)
    obs, _ = env.reset(seed=seed)
    steps: list[tuple[tuple[float, ...], str]] = []
    total = 0.0
    while True:
        s = task.observation(obs)
        if not np.all(np.isfinite(s)):
            break
        action = policy.act(s)
        shown = str(action) if task.discrete else "[" + ", ".join(f"{v:.2f}" for v in np.atleast_1d(action)) + "]"
        steps.append((tuple(float(v) for v in s), shown))
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        if terminated or truncated:
            break
    return total, steps
