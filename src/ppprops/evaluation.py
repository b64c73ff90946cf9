"""Runs a linear policy on a task and turns the episodes into one raw feedback record.

This is client-side code: it sees raw parameters and raw returns. Nothing here may be imported
by ``ppprops.wire``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .policy import LinearPolicy
from .tasks.base import Diagnostic, Task


@dataclass(frozen=True)
class Feedback:
    """Raw feedback of one candidate: mean return, mean reward components, aggregated diagnostics."""

    ret: float
    components: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, Diagnostic] = field(default_factory=dict)
    episode_returns: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "return": self.ret,
            "components": self.components,
            "diagnostics": self.diagnostics,
            "episode_returns": list(self.episode_returns),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Feedback:
        return cls(
            ret=float(d["return"]),
            components={k: float(v) for k, v in d["components"].items()},
            diagnostics=dict(d["diagnostics"]),
            episode_returns=tuple(float(v) for v in d.get("episode_returns", ())),
        )


@dataclass(frozen=True)
class Episode:
    ret: float
    components: dict[str, float]
    diagnostics: dict[str, Diagnostic]


def make_policy(task: Task, theta: NDArray[np.floating], env: Any) -> LinearPolicy:
    space = env.action_space
    low = getattr(space, "low", None) if not task.discrete else None
    high = getattr(space, "high", None) if not task.discrete else None
    return LinearPolicy.from_flat(theta, task.n_s, task.n_a, discrete=task.discrete, low=low, high=high)


def run_episode(task: Task, env: Any, policy: LinearPolicy, seed: int) -> Episode:
    """One episode. A non-finite observation or reward ends it and is marked, never propagated."""
    recorder = task.feedback()
    obs, info = env.reset(seed=seed)
    total = 0.0
    steps = 0
    terminated = truncated = False
    numerical_fault = False
    while True:
        s = task.observation(obs)
        if not np.all(np.isfinite(s)):
            numerical_fault = True
            break
        obs, reward, terminated, truncated, info = env.step(policy.act(s))
        reward = float(reward)
        if not np.isfinite(reward):
            numerical_fault = True
            break
        steps += 1
        total += reward
        recorder.step(obs, reward, info)
        if terminated or truncated:
            break
    fb = recorder.finish(terminated=bool(terminated), truncated=bool(truncated), steps=steps, info=info)
    diagnostics = dict(fb.diagnostics)
    if numerical_fault:
        diagnostics["numerical_fault"] = 1.0
    return Episode(ret=total, components=dict(fb.components), diagnostics=diagnostics)


def aggregate(episodes: Sequence[Episode]) -> Feedback:
    """Mean of returns and components; numeric diagnostics averaged, categorical ones counted."""
    n = len(episodes)
    ret = float(np.mean([e.ret for e in episodes]))
    comp_keys = list(dict.fromkeys(k for e in episodes for k in e.components))
    components = {k: float(np.mean([e.components.get(k, 0.0) for e in episodes])) for k in comp_keys}
    diag_keys = list(dict.fromkeys(k for e in episodes for k in e.diagnostics))
    diagnostics: dict[str, Diagnostic] = {}
    for k in diag_keys:
        values = [e.diagnostics.get(k) for e in episodes]
        if all(isinstance(v, float) for v in values):
            diagnostics[k] = float(np.mean(values))  # type: ignore[arg-type]
        elif n == 1:
            diagnostics[k] = str(values[0])
        else:
            counts = Counter(str(v) for v in values)
            diagnostics[k] = ", ".join(f"{name} x{c}" for name, c in counts.most_common())
    return Feedback(ret=ret, components=components, diagnostics=diagnostics, episode_returns=tuple(e.ret for e in episodes))


class Evaluator:
    """Keeps one environment per task alive across candidates (making envs can be slow)."""

    def __init__(self, task: Task) -> None:
        self.task = task
        self._env: Any = None

    @property
    def env(self) -> Any:
        if self._env is None:
            self._env = self.task.make_env()
        return self._env

    def evaluate(self, theta: NDArray[np.floating], seeds: Sequence[int]) -> Feedback:
        policy = make_policy(self.task, theta, self.env)
        return aggregate([run_episode(self.task, self.env, policy, s) for s in seeds])

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None

    def __enter__(self) -> Evaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
