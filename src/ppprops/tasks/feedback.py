"""Feedback read from the env's ``info``: reward components and diagnostics declared by info key.

A task declares each component or diagnostic by name with the info key it comes from. A key may be
a path into a dict-valued info entry (``rewards.collision_reward``); ``rewards.*`` asks for every
entry of that dict, which only a step of the env shows: ``ppprops.tasks.check.check_task`` (``ppprops
task check``) expands it in an episode the user asks for; loading a task refuses it.

Components are summed over the episode and are reward-valued (scaled with the return under
PP-ProPS). Diagnostics are reduced over the episode (``last`` value by default, or ``mean``,
``sum``, ``min``, ``max``) and never scaled.

Loading a task never steps its env, so the declaration is checked by the episodes that use it:
in every episode, each component must be in the env's info at the first step and each diagnostic
at some step of an episode that ends, every one a number (``FeedbackKeyError``, one line naming
the key, the info keys there are and the closest one).
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from .base import Diagnostic, EpisodeFeedback

REDUCE = ("last", "mean", "sum", "min", "max")
MISSING = object()
RESERVED = ("episode_length",)  # computed by ppprops for every task


class FeedbackKeyError(ConfigError):
    """A declared component or diagnostic is missing from the env's info, or not a scalar there."""


@dataclass(frozen=True)
class InfoKey:
    """One declared component or diagnostic: its name, the info key (or path) it is read from, how it is reduced."""

    name: str
    info: str
    reduce: str = "last"

    def to_json(self) -> dict[str, str]:
        """The stored form."""
        return {"name": self.name, "info": self.info, "reduce": self.reduce}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> InfoKey:
        """The inverse of ``to_json``."""
        return cls(name=str(d["name"]), info=str(d["info"]), reduce=str(d.get("reduce", "last")))


def lookup(info: Mapping[str, Any], path: str) -> Any:
    """``info[path]``, else the dotted path walked through dict values; ``MISSING`` if absent."""
    if path in info:
        return info[path]
    node: Any = info
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return MISSING
        node = node[part]
    return node


def scalar(value: Any) -> float | str | None:
    """A number, bool, size-1 array or string as a float (or the string); None for anything else."""
    if isinstance(value, (bool, int, float, np.bool_, np.number)):
        return float(value)
    if isinstance(value, np.ndarray) and value.size == 1 and value.dtype.kind in "biuf":
        return float(value.reshape(-1)[0])
    if isinstance(value, str):
        return value
    return None


def describe_keys(info: Mapping[str, Any]) -> str:
    """The keys of an ``info`` dict as one comma-separated list ("none" when empty), for error messages."""
    return ", ".join(map(str, info)) or "none"


def check_value(task: str, kind: str, key: InfoKey, info: Mapping[str, Any], *, where: str) -> float | str | None:
    """The key's value in ``info``, checked: a dict, a non-scalar, or a string component is a FeedbackKeyError.

    Returns None when the key is absent (the caller decides whether that is an error).
    """
    value = lookup(info, key.info)
    if value is MISSING:
        return None
    flag = "--component" if kind == "component" else "--diagnostic"
    if isinstance(value, Mapping):
        entries = ", ".join(map(str, value)) or "empty"
        raise FeedbackKeyError(
            f"{task}: {kind} {key.info!r} is a dict in the env's info ({entries}), not a number; name an entry "
            f"({flag} {key.info}.{next(iter(value), 'KEY')}), or list them all with `ppprops task check` and {flag} '{key.info}.*'"
        )
    v = scalar(value)
    if v is None or (kind == "component" and isinstance(v, str)):
        shape = f" of shape {value.shape}" if isinstance(value, np.ndarray) else ""
        raise FeedbackKeyError(f"{task}: {kind} {key.info!r} is not a number in the env's info "
                               f"(it is a {type(value).__name__}{shape}, {where})")  # fmt: skip
    return v


def missing_key(task: str, kind: str, key: InfoKey, info: Mapping[str, Any], *, where: str) -> FeedbackKeyError:
    """The one-line error for a declared key the env's ``info`` lacks ``where`` (e.g. "at step 3"), with a close match as hint."""
    close = difflib.get_close_matches(key.info, [str(k) for k in info], n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else ""
    return FeedbackKeyError(f"{task}: {kind} {key.info!r} is not in the env's info {where} (its keys: {describe_keys(info)}){hint}")


@dataclass(frozen=True)
class InfoFeedback:
    """Recorder factory: sums components, reduces diagnostics, counts steps as ``episode_length``."""

    task: str
    components: tuple[InfoKey, ...] = ()
    diagnostics: tuple[InfoKey, ...] = ()

    def __call__(self) -> _InfoRecorder:
        """A fresh recorder for one episode."""
        return _InfoRecorder(self)


class _InfoRecorder:
    def __init__(self, spec: InfoFeedback) -> None:
        self.spec = spec
        self.sums = {k.name: 0.0 for k in spec.components}
        self.values: dict[str, list[float | str]] = {}
        self.steps = 0

    def step(self, obs: NDArray[Any], reward: float, info: Mapping[str, Any]) -> None:
        self.steps += 1
        for k in self.spec.components:
            v = check_value(self.spec.task, "component", k, info, where="during a run")
            if v is not None:  # absent on a later step (present on the first): contributes nothing
                self.sums[k.name] += float(v)
            elif self.steps == 1:
                raise missing_key(self.spec.task, "component", k, info, where="at the first step")
        for k in self.spec.diagnostics:
            v = check_value(self.spec.task, "diagnostic", k, info, where="during a run")
            if v is not None:
                self.values.setdefault(k.name, []).append(v)

    def finish(self, *, terminated: bool, truncated: bool, steps: int, info: Mapping[str, Any]) -> EpisodeFeedback:
        if terminated or truncated:  # an episode cut short (a numerical fault) may end before a diagnostic shows
            unseen = [k for k in self.spec.diagnostics if k.name not in self.values]
            if unseen:
                raise missing_key(self.spec.task, "diagnostic", unseen[0], info, where="at any step of an episode")
        diag: dict[str, Diagnostic] = {"episode_length": float(steps)}
        for k in self.spec.diagnostics:
            seen = self.values.get(k.name)
            if seen:
                diag[k.name] = reduce(seen, k.reduce)
        return EpisodeFeedback(components=dict(self.sums), diagnostics=diag)


def reduce(values: list[float | str], how: str) -> Diagnostic:
    """Reduce a diagnostic's per-step values by ``how``: last, mean, sum, min or max (text values: the last)."""
    if how == "last" or any(isinstance(v, str) for v in values):
        return values[-1]
    nums = [float(v) for v in values]
    return {"mean": float(np.mean(nums)), "sum": float(np.sum(nums)), "min": min(nums), "max": max(nums)}[how]
