"""What an env returns from ``reset`` and ``step``, checked against what it declares, at every call.

An env that returns something malformed does not raise, so without these checks the first sign of
it is an error deep in the policy's arithmetic (a traceback), or worse, a number that is silently
wrong (a Discrete observation out of range indexes the one-hot table from its end). The checks are
those of Gymnasium's passive env checker (``gymnasium.utils.passive_env_checker``:
``env_reset_passive_checker``, ``env_step_passive_checker``, ``check_obs``), which only warns; here
each is a problem in one line that names the value and what was expected:

- ``reset`` returns a tuple ``(observation, info)``, ``step`` a tuple of five
  ``(observation, reward, terminated, truncated, info)`` (four values are the old Gym API);
- the observation fits the declared observation space: for a ``Box`` (or ``MultiBinary``) an array
  of numbers of the space's shape, for a ``Discrete`` an integer in the space's range, for a
  ``Dict`` a mapping whose entries the policy sees fit their own spaces;
- the reward is a real number (an int, a float, a numpy scalar or a 0-d array; not None, a text, a
  list, a complex number);
- ``terminated`` and ``truncated`` are booleans (or the integers 0 and 1);
- ``info`` is a dict.

Values inside the bounds of a ``Box`` are not required (Gymnasium only warns about them, and many
envs declare loose bounds), nor is the space's exact float dtype: a float64 observation of a
float32 space is fine. NaN and infinite values are not malformed: the episode loop ends such an
episode and marks it (``evaluation.run_episode``). Each check costs a type test and a shape
comparison when the value is well-formed (benchmarks/bench_eval.py measures the episode loop).
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any

import numpy as np

# Scalar types that are real numbers, for the reward's fast path (anything else takes the slow one).
_REAL_TYPES = frozenset({float, int, np.float64, np.float32, np.float16, np.int64, np.int32, np.int16, np.int8, np.uint64,
                         np.uint32, np.uint16, np.uint8, bool, np.bool_})
_NUMERIC_KINDS = "biuf"  # numpy dtype kinds of numbers: bool, int, unsigned, float


def show(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters, for a problem line."""
    text = repr(value)
    if isinstance(value, np.ndarray):
        text = np.array2string(value, threshold=8, edgeitems=2, separator=", ")
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _kind(value: Any) -> str:
    """What a value is, in words: ``a str``, ``a list of 5``, ``an array of shape (5,) and dtype float64``."""
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    if isinstance(value, (list, tuple)):
        return f"a {type(value).__name__} of {len(value)}"
    name = type(value).__name__
    return f"{'an' if name[:1] in 'aeiou' else 'a'} {name}"


def _not(what: str, value: Any, expected: str) -> str:
    """``what VALUE is KIND, not EXPECTED`` (``what None is not EXPECTED`` for None)."""
    if value is None:
        return f"{what} None is not {expected}"
    return f"{what} {show(value)} is {_kind(value)}, not {expected}"


class SpaceCheck:
    """The observation check of one observation space (``OutputCheck``): ``problem(obs)`` is None
    for an observation that fits, else what is wrong, in words."""

    def __init__(self, space: Any, keys: tuple[str, ...] | None = None) -> None:
        from gymnasium import spaces

        self.space = space
        self.kind = "other"
        self.shape: tuple[int, ...] = ()
        self.entries: dict[str, SpaceCheck] = {}
        if isinstance(space, (spaces.Box, spaces.MultiBinary)):
            self.kind, self.shape = "array", tuple(space.shape)
        elif isinstance(space, spaces.Discrete):
            self.kind = "discrete"
            self.low, self.high = int(space.start), int(space.start) + int(space.n)  # [low, high)
        elif isinstance(space, spaces.Dict):
            self.kind = "dict"
            self.entries = {k: SpaceCheck(space.spaces[k]) for k in (keys if keys is not None else space.spaces) if k in space.spaces}

    def problem(self, obs: Any, what: str = "observation") -> str | None:
        """None when ``obs`` fits the space (the fast path: a type test and a shape comparison), else the problem."""
        if self.kind == "array":
            if type(obs) is np.ndarray and obs.shape == self.shape and obs.dtype.kind in _NUMERIC_KINDS:
                return None
            return self._array_problem(obs, what)
        if self.kind == "discrete":
            if isinstance(obs, (int, np.integer)) and not isinstance(obs, (bool, np.bool_)) and self.low <= obs < self.high:
                return None
            return self._discrete_problem(obs, what)
        if self.kind == "dict":
            if not isinstance(obs, Mapping):
                return _not(what, obs, f"a dict (its observation space is {self._space()})")
            for key, check in self.entries.items():
                if key not in obs:
                    return f"{what} has no entry {key!r} (its entries: {', '.join(map(str, obs)) or 'none'})"
                found = check.problem(obs[key], f"{what} entry {key!r}")
                if found is not None:
                    return found
        return None

    def _space(self) -> str:
        return " ".join(str(self.space).split())

    def _array_problem(self, obs: Any, what: str) -> str | None:
        try:
            arr = np.asarray(obs)
        except (ValueError, TypeError):  # a ragged list
            arr = None
        if arr is None or arr.dtype.kind not in _NUMERIC_KINDS:
            space = f"(its observation space is {self._space()})"
            if isinstance(obs, np.ndarray):
                return f"{what} {show(obs)} has dtype {obs.dtype}, not numbers {space}"
            return _not(what, obs, f"an array of numbers {space}")
        if arr.shape != self.shape:
            return f"{what} has shape {arr.shape}, but its observation space {self._space()} has shape {self.shape}"
        return None

    def _discrete_problem(self, obs: Any, what: str) -> str | None:
        value = obs
        if isinstance(obs, np.ndarray) and obs.shape == () and obs.dtype.kind in "iu":
            value = obs.item()  # a 0-d integer array: fine when in range
        if not isinstance(value, (int, np.integer)) or isinstance(value, (bool, np.bool_)):
            return _not(what, obs, f"an integer (its observation space is {self._space()})")
        if not self.low <= value < self.high:
            return f"{what} {value} is outside its observation space {self._space()} (integers {self.low} to {self.high - 1})"
        return None


def reward_problem(reward: Any) -> str | None:
    """None when ``reward`` is a real number (any value, NaN and infinities included), else what is wrong."""
    if type(reward) in _REAL_TYPES:
        return None
    if isinstance(reward, np.ndarray):
        if reward.shape == () and reward.dtype.kind in _NUMERIC_KINDS:
            return None
        return f"reward {show(reward)} is {_kind(reward)}, not a number"
    if isinstance(reward, (numbers.Real, np.integer, np.floating)):
        return None
    if reward is None:
        return "reward None is not a number"
    if isinstance(reward, (complex, np.complexfloating)):
        return f"reward {show(reward)} is a complex number, not a real one"
    return f"reward {show(reward)} is {_kind(reward)}, not a number"


def flag_problem(name: str, value: Any) -> str | None:
    """None when ``value`` (``terminated`` or ``truncated``) is a boolean or the integer 0 or 1, else what is wrong."""
    if value is True or value is False or type(value) is np.bool_:
        return None
    if isinstance(value, (int, np.integer)) and value in (0, 1):
        return None
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "biu" and value.item() in (0, 1):
        return None
    return _not(name, value, "a bool")


def info_problem(info: Any) -> str | None:
    """None when ``info`` is a dict (a mapping), else what is wrong."""
    if type(info) is dict or isinstance(info, Mapping):
        return None
    return _not("info", info, "a dict")


class OutputCheck:
    """Checks what one env returns from ``reset`` and ``step`` (module docstring).

    ``reset(result)`` and ``step(result)`` return the problem in words, or None when the value is
    well-formed; the caller says where (``call_line``). ``keys``: the entries of a Dict observation
    the policy sees (the others are not checked).
    """

    def __init__(self, env: Any, keys: tuple[str, ...] | None = None) -> None:
        self.observation = SpaceCheck(env.observation_space, keys)

    def reset(self, result: Any) -> str | None:
        """The problem of ``env.reset``'s return value, or None."""
        if type(result) is not tuple or len(result) != 2:
            if isinstance(result, tuple):
                return f"it returned {len(result)} values, not 2 (observation, info)"
            return f"it returned {_kind(result)}, not a tuple (observation, info) (Gymnasium's reset returns both)"
        return self.observation.problem(result[0]) or info_problem(result[1])

    def step(self, result: Any) -> str | None:
        """The problem of ``env.step``'s return value, or None."""
        if type(result) is not tuple or len(result) != 5:
            if isinstance(result, tuple) and len(result) == 4:
                return ("it returned 4 values (the old Gym API: observation, reward, done, info), not 5 (observation, reward, "
                        "terminated, truncated, info)")
            if isinstance(result, tuple):
                return f"it returned {len(result)} values, not 5 (observation, reward, terminated, truncated, info)"
            return f"it returned {_kind(result)}, not a tuple (observation, reward, terminated, truncated, info)"
        obs, reward, terminated, truncated, info = result
        return (self.observation.problem(obs) or reward_problem(reward) or flag_problem("terminated", terminated)
                or flag_problem("truncated", truncated) or info_problem(info))


def call_line(task: str, call: str, seed: int, problem: str) -> str:
    """The one line of a malformed value, worded as the line of an env that raised (``evaluation.EpisodeError``):
    ``the env of task NAME returned a malformed value in step 3 (episode seed 812): reward None is not a number``.

    ``call`` is ``reset`` or ``step N`` (N counts from 1: the episode's first step is step 1).
    """
    return f"the env of task {task} returned a malformed value in {call} (episode seed {seed}): {problem}"


__all__ = ["OutputCheck", "SpaceCheck", "call_line", "flag_problem", "info_problem", "reward_problem", "show"]
