"""Recording one episode as a state -> action sequence (R2PO's trajectory evidence).

Episodes are seeded, so re-running the median episode of an evaluation reproduces it exactly
without storing every trajectory of every evaluation. The episode runs through
``evaluation.run_episode``, with its numerical-fault checks and step cap.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .evaluation import make_policy, run_episode, step_cap
from .tasks.base import Task

Step = tuple[tuple[float, ...], str]  # (policy input, action as shown to the critic)


def record_rollout(task: Task, env: Any, theta: np.ndarray, seed: int) -> tuple[float, list[Step]]:
    """The return and the (state, action) steps of one episode of the linear policy ``theta``.

    ``theta`` is the raw flat parameter vector, shape (D,); each step holds the task's observation
    vector (n_s floats) and the action as text (a discrete index, or a list with two decimals).
    An episode that hits a non-finite observation or reward ends there (as in the evaluation).

    Raises:
        EpisodeLimitError: the env has no time limit and the episode did not end.
    """
    steps: list[Step] = []

    def record(s: NDArray[np.float64], action: Any) -> None:
        shown = str(action) if task.discrete else "[" + ", ".join(f"{v:.2f}" for v in np.atleast_1d(action)) + "]"
        steps.append((tuple(float(v) for v in s), shown))

    episode = run_episode(task, env, make_policy(task, theta, env), seed, max_steps=step_cap(env), on_step=record)
    return episode.ret, steps
