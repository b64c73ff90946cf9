"""Warm starts: the controllers a user already has, evaluated first, in the warm-up's place.

``--init-policy PATH`` (repeatable; ``init_policies=[...]`` in ``ppprops.search`` and
``create_study``) names a policy to start from: a ppprops policy file of the same task (an earlier
run's ``best_policy.json``), or a JSON object with ``W`` (n_s rows of n_a values: ``u = s @ W +
b``) and ``b``, or with ``theta`` (the D values in the flat layout: W row by row, then b). In
Python a policy may also be such a mapping, or an array of shape (D,).

The given policies are the run's first trials, in order (source ``init``), and count towards the
warm-up: trial i < k is given policy i, and the warm-up's other trials are the draws they would
have been without them (each warm-up draw is keyed by its trial number, ``GivenFirst``). Like every
candidate they are encoded under the run's secrets before they reach a prompt, and the audit
checks them like any raw value.

A study also takes a given policy at any time before its search is over (``Study.enqueue``,
``ppprops study enqueue DIR PATH``): queued in the store, it is the next new trial asked, in the
place of that trial's warm-up draw or LLM proposal (CMA-ES and R2PO ask their own trials: for
them, within the warm-up only).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ConfigError, PPPropsError
from .proposers.base import Proposal, SearchProposer
from .values import Candidate

if TYPE_CHECKING:
    from .store import RunStore
    from .tasks import Task

SOURCE = "init"  # the candidates' source


def init_thetas(policies: Sequence[Any], task: Task, *, box: tuple[float, float], warmup: int,
                flag: str = "--init-policy") -> tuple[tuple[float, ...], ...]:  # fmt: skip
    """The raw parameters (D values each) of the given policies, checked against ``task``.

    Each of ``policies`` is a path (str or os.PathLike) to a policy file or a JSON object, a
    mapping with ``W`` and ``b`` or with ``theta``, or a sequence of D numbers (module docstring).
    ``flag`` starts a path's error line (``--init-policy PATH: ...``; "" for the path alone).

    Raises:
        ConfigError: one line naming the policy: a missing or unreadable file, not JSON, another
            task's policy file, a shape that is not this task's, a value that is not finite or lies
            outside ``box``, more policies than the ``warmup`` holds.
    """
    if len(policies) > warmup:
        raise ConfigError(f"--init-policy: {len(policies)} policies given, more than the warm-up holds (--warmup {warmup}); "
                          "the given policies take the warm-up's first places")  # fmt: skip
    return tuple(tuple(float(v) for v in _theta(p, task, box, flag)) for p in policies)


def _theta(policy: Any, task: Task, box: tuple[float, float], flag: str) -> np.ndarray:
    if isinstance(policy, str | os.PathLike):
        where = f"{flag} {policy}".strip()
        doc = _read(Path(policy), where)
    else:
        where, doc = "init policy", policy
    if isinstance(doc, Mapping) and "format" in doc:
        theta = _policy_file(Path(policy), doc, task, where) if isinstance(policy, str | os.PathLike) else _policy_doc(doc, task, where)
    elif isinstance(doc, Mapping):
        theta = _mapping(doc, task, where)
    elif isinstance(doc, Sequence | np.ndarray) and not isinstance(doc, str):
        theta = _numbers(doc, where, "theta")
    else:
        raise ConfigError(f"{where} must be a policy file, a JSON object with W and b or with theta, or D = {task.D} numbers")
    if theta.shape != (task.D,):
        raise ConfigError(f"{where} has {theta.size} parameters; task {task.name} has D = {task.D} ({task.policy.label()})")
    lo, hi = box
    out = np.flatnonzero((theta < lo) | (theta > hi))
    if out.size:
        j = int(out[0])
        raise ConfigError(f"{where}: theta[{j}] = {theta[j]:g} lies outside the box {lo:g},{hi:g} ({out.size} of {theta.size} values do): "
                          "widen --box to hold it")  # fmt: skip
    return theta


def _read(path: Path, where: str) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{where}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        from .fileio import read_error

        raise ConfigError(f"{where} cannot be read: {read_error(e)}") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{where} is not JSON ({e.msg} at line {e.lineno})") from None


def _policy_file(path: Path, doc: Mapping[str, Any], task: Task, where: str) -> np.ndarray:
    """A ppprops policy file: of this task (by name), read and checked by ``policy_file.read_policy``."""
    from .policy_file import read_policy

    _same_task(doc, task, where)
    try:
        _, theta = read_policy(path)
    except PPPropsError as e:
        raise ConfigError(str(e)) from None
    return np.asarray(theta, dtype=np.float64)


def _policy_doc(doc: Mapping[str, Any], task: Task, where: str) -> np.ndarray:
    """A policy file's document given as a mapping (Python): its task checked, then its theta or W and b."""
    _same_task(doc, task, where)
    return _numbers(doc["theta"], where, "theta") if "theta" in doc else _mapping(doc, task, where)


def _same_task(doc: Mapping[str, Any], task: Task, where: str) -> None:
    if doc.get("task") != task.name:
        raise ConfigError(f"{where} is a policy of task {doc.get('task')!r}, not of {task.name}")


def _mapping(doc: Mapping[str, Any], task: Task, where: str) -> np.ndarray:
    if "theta" in doc:
        if "W" in doc or "b" in doc:
            raise ConfigError(f"{where} gives theta and W/b: give one of them")
        return _numbers(doc["theta"], where, "theta")
    if "W" not in doc or "b" not in doc:
        raise ConfigError(f"{where} needs W and b (u = s @ W + b), or theta")
    if not task.policy.is_linear:
        raise ConfigError(f"{where} gives W and b, a linear policy; task {task.name} searches {task.policy.label()}: give theta")
    W, b = _numbers(doc["W"], where, "W", flat=False), _numbers(doc["b"], where, "b")
    n_s, n_a = task.n_s, task.n_a
    if W.shape == (n_a, n_s) and n_a != n_s:
        raise ConfigError(f"{where}: W is {n_a}x{n_s}, the transpose of what u = s @ W + b takes ({n_s}x{n_a}: one row per "
                          "observation value); an LQR gain K of u = -K s is W = -K^T")  # fmt: skip
    if W.shape != (n_s, n_a) or b.shape != (n_a,):
        raise ConfigError(f"{where}: W must be {n_s}x{n_a} (one row per observation value) and b of length {n_a}, got W of shape "
                          f"{'x'.join(map(str, W.shape))} and b of length {b.size}")  # fmt: skip
    return np.concatenate([W.reshape(-1), b])


def _numbers(value: Any, where: str, name: str, *, flat: bool = True) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: {name} must hold numbers only") from None
    if flat and arr.ndim != 1:
        raise ConfigError(f"{where}: {name} must be a flat list of numbers, got shape {'x'.join(map(str, arr.shape))}")
    if not np.all(np.isfinite(arr)):
        bad = next(v for v in arr.reshape(-1) if not math.isfinite(v))
        raise ConfigError(f"{where}: {name} holds {bad}, not a finite number")
    return arr


TAKES_GIVEN = ("warmup", "llm", "random")  # the phases whose trials a queued policy may take (CMA-ES and R2PO ask their own)


def enqueue(store: RunStore, theta: Sequence[float], *, task: Task, box: tuple[float, float], search_takes: bool, warmup: int,
            planned_end: int, note: str = "") -> int:  # fmt: skip
    """Queue a given policy (raw, shape (D,)) to be the study's next new trial: it takes that trial's
    place in the warm-up or the search (its draw or its proposal is never made), encoded like any
    candidate. Returns its place in the queue (1: the next new trial). Call it under the study's lock.

    Raises:
        ConfigError: the policy's shape or values (``init_thetas``), or no place left for it: the
            search is over, or the method's search asks its own trials (``search_takes`` False:
            CMA-ES, R2PO) and the warm-up has no place left.
    """
    [checked] = init_thetas([list(theta)], task, box=box, warmup=1)
    queue = store.queued()
    first = store.next_number() + len(queue)  # the trial it would be
    last = planned_end if search_takes else warmup
    if first >= last:
        where = "its search is over" if first >= planned_end else "its warm-up is asked, and the method's search asks its own trials"
        raise ConfigError(f"no place left for a given policy: {where}")
    store.set_queued([*queue, {"theta": list(checked), "note": note or "given policy"}])
    return len(queue) + 1


def take_queued(queue: list[dict[str, Any]], phase: str, iterations: Sequence[int]) -> list[Proposal]:
    """The proposals of the queued policies ``iterations`` take (the first ones; none in a phase not
    in ``TAKES_GIVEN``), removed from ``queue``."""
    if phase not in TAKES_GIVEN:
        return []
    taken, queue[:] = queue[:len(iterations)], queue[len(iterations):]
    return [Proposal(theta=np.asarray(q["theta"], dtype=np.float64), source=SOURCE, note=str(q["note"])) for q in taken]


class GivenFirst(SearchProposer):
    """The warm-up with the given policies first: iteration i < k proposes given policy i (source
    ``init``), any other the warm-up sampler's draw i (the draw it would have been without them)."""

    def __init__(self, thetas: Sequence[Sequence[float]], warmup: SearchProposer) -> None:
        self.thetas = [np.asarray(t, dtype=np.float64) for t in thetas]
        self.warmup = warmup

    def ask(self, iteration: int) -> Proposal:
        """Given policy ``iteration``, or the warm-up's draw ``iteration``."""
        if iteration < len(self.thetas):
            return Proposal(theta=self.thetas[iteration].copy(), source=SOURCE, note=f"given policy {iteration + 1}")
        return self.warmup.ask(iteration)

    def tell(self, candidate: Candidate) -> None:
        """Nothing: neither depends on results."""


__all__ = ["GivenFirst", "SOURCE", "TAKES_GIVEN", "enqueue", "init_thetas", "take_queued"]
