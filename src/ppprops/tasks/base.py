"""What the search loop knows about a task: the Task, its observation adapter, its feedback recorder.

The loop only ever sees a ``Task``. Tasks are data: each is built from a task file (TOML) or the
equivalent ``TaskSpec`` (``ppprops.tasks.spec``), never by touching the loop.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from ..policy import LINEAR, PolicySpec
from ..values import Diagnostic

ActionType = Literal["continuous", "discrete"]


@dataclass(frozen=True)
class EpisodeFeedback:
    """What one episode yields besides its return: reward components (sums) and diagnostics."""

    components: dict[str, float]
    diagnostics: dict[str, Diagnostic]


class EpisodeRecorder(Protocol):
    """Accumulates one episode's feedback step by step."""

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        """Add one step: the raw observation after it, its reward (reward units), and the env's ``info``."""
        ...

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        """The episode's summed components and reduced diagnostics, after ``steps`` steps."""
        ...


class ObservationAdapter(Protocol):
    """Maps the environment's observation to the policy's state vector s (length n_s)."""

    @property
    def names(self) -> tuple[str, ...]:
        """One name per state value, in the order of s."""
        ...

    def __call__(self, obs: Any) -> NDArray[np.float64]:
        """The state vector s, shape (n_s,), float64, from one raw observation."""
        ...


@dataclass(frozen=True)
class Selection:
    """The policy's state s from a raw observation: Dict entries, one-hot, then chosen indices.

    The same four steps, in this order, are the deployment recipe of the policy file (README): a
    Dict observation keeps ``keys`` (each flattened, concatenated in this order); a Discrete
    observation becomes a one-hot vector of length ``one_hot[0]`` (its value minus ``one_hot[1]``,
    the space's start); the result is flattened to float64; ``indices`` keep some of its values.
    """

    names: tuple[str, ...]
    indices: tuple[int, ...] | None = None
    keys: tuple[str, ...] | None = None
    one_hot: tuple[int, int] | None = None  # (n, start) of a Discrete observation

    def __call__(self, obs: Any) -> NDArray[np.float64]:
        """The state s, shape (n_s,), from a raw observation (the four steps of the class docstring)."""
        if self.keys is not None:
            obs = np.concatenate([np.ravel(obs[k]) for k in self.keys])
        if self.one_hot is not None:
            obs = np.eye(self.one_hot[0])[obs - self.one_hot[1]]
        flat = np.ravel(np.asarray(obs, dtype=np.float64))
        return flat if self.indices is None else flat[list(self.indices)]

    def to_json(self) -> dict[str, Any]:
        """The stored form (in run configs and policy files)."""
        return {
            "names": list(self.names),
            "keys": None if self.keys is None else list(self.keys),
            "one_hot": None if self.one_hot is None else {"n": self.one_hot[0], "start": self.one_hot[1]},
            "indices": None if self.indices is None else list(self.indices),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Selection:
        """The inverse of ``to_json``; KeyError for a missing ``names``."""
        oh = d.get("one_hot")
        return cls(
            names=tuple(d["names"]),
            indices=None if d.get("indices") is None else tuple(int(i) for i in d["indices"]),
            keys=None if d.get("keys") is None else tuple(d["keys"]),
            one_hot=None if oh is None else (int(oh["n"]), int(oh["start"])),
        )


@dataclass(frozen=True)
class TaskText:
    """The prose a prompt may use about a task (from its task file, see ``ppprops.tasks.spec``).

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



class NoEnvError(ConfigError):
    """The task has no env (a robot outside Python): nothing in ppprops can run its episodes."""


@dataclass(frozen=True)
class NoEnv:
    """``Task.setup`` of a task without env: called before an env is made, it refuses in one line (``NoEnvError``)."""

    task: str

    def __call__(self) -> None:
        """Raise ``NoEnvError`` naming the task and how it is driven instead."""
        raise NoEnvError(f"task {self.task} has no env: it describes a robot outside Python, whose episodes only its own "
                         "driver runs; search it with ask/tell (`ppprops ask` / `ppprops tell`, or Study.ask / Study.tell), "
                         "and evaluate its policy on the robot")  # fmt: skip


@dataclass(frozen=True)
class Task:
    """Everything the loop needs to know about an environment configuration.

    Tasks are built from a ``TaskSpec`` (``spec``: the declaration as data, stored with every run);
    a Task made by hand without one works in this process and is sent whole to worker processes.
    A task without env (``has_env`` False: a robot outside Python, driven with ask/tell) has
    ``env_id == ""``, declares its continuous action bounds (``action_low`` / ``action_high``, one
    value per action), and its ``make_env`` raises ``NoEnvError``. ``prompt_name`` is the name the
    task file allows a prompt to show the provider (None: not set).
    """

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
    spec: Any = field(default=None, compare=False, repr=False)  # the TaskSpec it was built from
    prompt_name: str | None = None
    action_low: tuple[float, ...] | None = None  # declared bounds (a task without env); else the env's action space
    action_high: tuple[float, ...] | None = None
    policy: PolicySpec = LINEAR  # the policy family searched (``ppprops.policy``): the paper's linear one by default

    @property
    def has_env(self) -> bool:
        """False for a task without env (a robot outside Python, driven with ask/tell): ``make_env`` raises."""
        return not isinstance(self.setup, NoEnv)

    @property
    def D(self) -> int:
        """D, the number of policy parameters (theta in R^D, paper Sec. II-A): (n_s + 1) n_a for the linear
        policy (layout of Eq. 10), the sum of the layers' (fan_in + 1) fan_out for an MLP (``PolicySpec``)."""
        return self.policy.param_count(self.n_s, self.n_a)

    @property
    def discrete(self) -> bool:
        """True for a Discrete action space (the policy takes the argmax of its scores)."""
        return self.action_type == "discrete"

    def make_env(self) -> Any:
        """A fresh env (the spec's recipe when there is one: the same ``gym.make`` as the policy file's).

        Raises:
            NoEnvError: the task has no env (``has_env`` is False).
            ConfigError: the env cannot be made (one line naming the cause; ``envs.EnvRecipe.make``).
        """
        import gymnasium as gym

        if isinstance(self.setup, NoEnv):
            self.setup()
        if self.spec is not None:
            return self.spec.env.make()
        if self.setup is not None:
            self.setup()
        return gym.make(self.env_id, disable_env_checker=True, **dict(self.env_kwargs))

    def action_bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """The continuous actions' (low, high), each of shape (n_a,); None for discrete actions.

        A task without env gives its declared bounds; a task with an env reads them from the env's
        action space, which makes the env (and closes it, never stepped).
        """
        if self.discrete:
            return None
        if self.action_low is not None and self.action_high is not None:
            return np.asarray(self.action_low, dtype=np.float64), np.asarray(self.action_high, dtype=np.float64)
        env = self.make_env()
        try:
            space = env.action_space
            shape = (self.n_a,)
            return (np.broadcast_to(np.asarray(space.low, dtype=np.float64), shape).copy(),
                    np.broadcast_to(np.asarray(space.high, dtype=np.float64), shape).copy())  # fmt: skip
        finally:
            env.close()

    def detailed_feedback(self) -> str:
        """This task's detailed feedback counted in words, for a note: ``4 reward components and 1
        diagnostic`` (``episode_length``, which every task with an env counts, left out); "" when
        it has none."""
        parts = []
        diagnostics = [d for d in self.diagnostics if d != "episode_length"]
        for n, what in ((len(self.components), "reward component"), (len(diagnostics), "diagnostic")):
            if n:
                parts.append(f"{n} {what}{'s' if n != 1 else ''}")
        return " and ".join(parts)

    def summary(self) -> dict[str, Any]:
        """The task's shape as a dict (name, env id, n_s, n_a, D, action type, feedback keys), for ``show`` and JSON output."""
        return {
            "name": self.name,
            "env_id": self.env_id,
            "n_s": self.n_s,
            "n_a": self.n_a,
            "D": self.D,
            "policy": self.policy.label(),
            "action_type": self.action_type,
            "components": list(self.components),
            "diagnostics": list(self.diagnostics),
        }


def check_names(task: Task, names: Sequence[str]) -> None:
    """Refuse a list of observation names whose length is not n_s (ValueError)."""
    if len(names) != task.n_s:
        raise ValueError(f"task {task.name}: {len(names)} observation names for n_s={task.n_s}")
