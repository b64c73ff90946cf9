"""A task is data: env id, kwargs, observation adapter, feedback extractor and a description.

The search loop only ever sees a ``Task``; adding an environment means adding one of these
(plus a description file), never touching the loop.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from ..policy import param_count

ActionType = Literal["continuous", "discrete"]
Diagnostic = float | str


@dataclass(frozen=True)
class EpisodeFeedback:
    """What one episode yields besides its return: reward components (sums) and diagnostics."""

    components: dict[str, float]
    diagnostics: dict[str, Diagnostic]


class EpisodeRecorder(Protocol):
    """Accumulates one episode's feedback step by step."""

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None: ...

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback: ...


class ObservationAdapter(Protocol):
    """Maps the environment's observation to the policy's state vector s (length n_s)."""

    names: tuple[str, ...]

    def __call__(self, obs: Any) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class FlatBox:
    """Flattens a Box observation, optionally keeping only some indices."""

    names: tuple[str, ...]
    indices: tuple[int, ...] | None = None

    def __call__(self, obs: Any) -> NDArray[np.float64]:
        flat = np.asarray(obs, dtype=np.float64).reshape(-1)
        return flat if self.indices is None else flat[list(self.indices)]


@dataclass(frozen=True)
class ComponentSums:
    """Sums the named info keys over an episode as reward components; counts steps as a diagnostic."""

    keys: tuple[str, ...] = ()
    diagnostic_keys: tuple[str, ...] = ()

    def __call__(self) -> EpisodeRecorder:
        return _SumRecorder(self.keys, self.diagnostic_keys)


class _SumRecorder:
    def __init__(self, keys: tuple[str, ...], diagnostic_keys: tuple[str, ...]) -> None:
        self.keys = keys
        self.diagnostic_keys = diagnostic_keys
        self.sums = dict.fromkeys(keys, 0.0)
        self.last: dict[str, Diagnostic] = {}

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        for k in self.keys:
            self.sums[k] += float(info.get(k, 0.0))
        for k in self.diagnostic_keys:
            if k in info:
                v = info[k]
                self.last[k] = float(v) if isinstance(v, (int, float, bool, np.number, np.bool_)) else str(v)

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        diag: dict[str, Diagnostic] = {"episode_length": float(steps)}
        diag.update(self.last)
        return EpisodeFeedback(components=dict(self.sums), diagnostics=diag)


@dataclass(frozen=True)
class TaskText:
    """The prose a prompt may use about a task. Loaded from a TOML file next to the task module.

    ``reward_structure`` may hold numbers (per-step rewards, limits) and is shown only when the
    preset discloses the reward structure; ``reward_hint`` is qualitative and safe for every preset.
    """

    summary: str
    observations: tuple[str, ...]
    actions: tuple[str, ...]
    reward_structure: str
    reward_hint: str
    hints: str = ""
    components: Mapping[str, str] = field(default_factory=dict)
    diagnostics: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def load(cls, package: str, filename: str) -> TaskText:
        raw = tomllib.loads(resources.files(package).joinpath(filename).read_text(encoding="utf-8"))
        return cls(
            summary=raw["summary"].strip(),
            observations=tuple(raw["observations"]),
            actions=tuple(raw["actions"]),
            reward_structure=raw["reward_structure"].strip(),
            reward_hint=raw["reward_hint"].strip(),
            hints=raw.get("hints", "").strip(),
            components=dict(raw.get("components", {})),
            diagnostics=dict(raw.get("diagnostics", {})),
        )


@dataclass(frozen=True)
class Task:
    """Everything the loop needs to know about an environment configuration."""

    name: str
    env_id: str
    n_s: int
    n_a: int
    action_type: ActionType
    observation: ObservationAdapter
    feedback: Callable[[], EpisodeRecorder]
    text: TaskText
    components: tuple[str, ...] = ()
    diagnostics: tuple[str, ...] = ("episode_length",)
    env_kwargs: Mapping[str, Any] = field(default_factory=dict)
    optimal_return: float | None = None
    setup: Callable[[], None] | None = None  # e.g. registering third-party envs before gym.make

    @property
    def D(self) -> int:
        return param_count(self.n_s, self.n_a)

    @property
    def discrete(self) -> bool:
        return self.action_type == "discrete"

    def make_env(self) -> Any:
        import gymnasium as gym

        if self.setup is not None:
            self.setup()
        return gym.make(self.env_id, disable_env_checker=True, **dict(self.env_kwargs))

    def summary(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "env_id": self.env_id,
            "n_s": self.n_s,
            "n_a": self.n_a,
            "D": self.D,
            "action_type": self.action_type,
            "components": list(self.components),
            "diagnostics": list(self.diagnostics),
        }


def check_names(task: Task, names: Sequence[str]) -> None:
    if len(names) != task.n_s:
        raise ValueError(f"task {task.name}: {len(names)} observation names for n_s={task.n_s}")
