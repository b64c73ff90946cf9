"""A round's candidates evaluated as Ray tasks (``ppprops run --parallel P --ray-address ADDRESS``).

``RayFleet`` is an ``evaluation.Fleet``: ``evaluate_each`` sends each candidate's episodes to the
cluster as one Ray task, which rebuilds the task from its ``tasks.task_ref`` handle (as the process
pool's workers do), keeps one env per Ray worker process, and returns the candidate's raw feedback,
or the one line of the ``EpisodeError`` that stopped it. An episode depends only on (task, theta,
seed), so the results are those of the local evaluator. Every node needs ppprops (and the extras
of the task) installed; Ray is the ``ray`` extra.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .evaluation import EpisodeError, aggregate, make_policy, run_episode, step_cap
from .ray_cluster import connect, import_ray
from .tasks import Task, resolve_task, task_ref
from .values import Feedback

_envs: dict[str, Any] = {}  # one env per task, per Ray worker process


def _episodes(ref: Any, theta: NDArray[np.floating], seeds: Sequence[int]) -> tuple[str, Any]:
    """In a Ray worker: ("ok", Feedback) of ``theta`` on ``seeds``, or ("failed", the EpisodeError's line)."""
    import json

    key = json.dumps(ref, sort_keys=True, default=str)
    if key not in _envs:
        task = resolve_task(ref)
        _envs[key] = (task, task.make_env())
    task, env = _envs[key]
    try:
        eps = [run_episode(task, env, make_policy(task, theta, env), int(s), max_steps=step_cap(env)) for s in seeds]
    except EpisodeError as e:
        return "failed", str(e)
    return "ok", aggregate(eps)


def _ray() -> Any:
    return import_ray("--ray-address")


class RayFleet:
    """Evaluate candidates as Ray tasks on the cluster at ``address`` (``local``: start Ray on this
    machine; ``auto``, ``ray://head:10001``, ...). One task per candidate, asking ``cpus`` CPUs.

    Raises MissingExtraError without the ``ray`` extra, ConfigError when the cluster cannot be
    reached (one line)."""

    def __init__(self, task: Task, address: str, *, cpus: float = 1.0) -> None:
        ray, self._started = connect(address, "--ray-address")
        self._remote = ray.remote(num_cpus=cpus)(_episodes)
        self._ref = task_ref(task)

    def evaluate_each(self, thetas: Sequence[NDArray[np.floating]],
                      seeds_list: Sequence[Sequence[int]]) -> list[Feedback | EpisodeError]:
        """One Feedback per candidate (or the EpisodeError that stopped it), in order, the
        candidates' episodes running side by side as Ray tasks."""
        ray = _ray()
        refs = [self._remote.remote(self._ref, np.asarray(t, dtype=np.float64), [int(s) for s in seeds])
                for t, seeds in zip(thetas, seeds_list, strict=True)]
        out: list[Feedback | EpisodeError] = []
        for kind, value in ray.get(refs):
            out.append(value if kind == "ok" else EpisodeError(value))
        return out

    def close(self) -> None:
        """Shut Ray down when this fleet started it."""
        if self._started:
            _ray().shutdown()
            self._started = False
