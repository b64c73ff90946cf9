"""The provider's view of a run: the distinct history entries it was shown, and what an attack returns."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..tasks.facts import PrivacyFacts
from .knowledge import facts_for
from .requests import Request
from .tokens import token_value

_INTEGER = re.compile(r"-?\d+")

if TYPE_CHECKING:
    from ..tasks.base import Task


@dataclass(frozen=True)
class Shown:
    """One distinct history entry as the provider saw it."""

    params: np.ndarray
    tols: np.ndarray
    ret: float
    ret_tol: float
    diagnostics: dict[str, str]
    first_call: int
    components: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class View:
    """Everything an attack may use: the transcript and public facts."""

    requests: tuple[Request, ...]
    entries: tuple[Shown, ...]
    warmup: tuple[Shown, ...]  # the entries of the first request: the warm-up, as Algorithm 1 starts
    facts: PrivacyFacts  # completed for the task (``knowledge.facts_for``)
    box: tuple[float, float]
    D: int
    memo: dict[str, object] = field(default_factory=dict, compare=False, hash=False)  # results attacks share
    # the task's public declaration (env id, observation, recorder), so simulator attacks can build
    # its env when that env is public; None when only the name is known
    task: Task | None = field(default=None, compare=False)
    # every printed parameter is an integer: the grid number format (wire.numbers), whose secret global
    # factor g in [G/2, G] (G public: client.codec.grid_scale) multiplies every a_j
    grid: bool = False

    @property
    def layer_box(self) -> tuple[Any, Any]:
        """Where the client keeps each parameter (public): ``box`` for the linear policy; an MLP's
        per-layer boxes (``PolicySpec.bounds``, two arrays of shape (D,)), which its prompt describes."""
        t = self.task
        if t is None or t.policy.is_linear or t.D != self.D:
            return self.box
        return t.policy.bounds(t.n_s, t.n_a, self.box)

    @property
    def init_box(self) -> tuple[Any, Any]:
        """Where the raw warm-up draws each parameter (public): ``box`` for the linear policy; an MLP's
        scaled initialisation per layer (``PolicySpec.init_bounds``, two arrays of shape (D,))."""
        t = self.task
        if t is None or t.policy.is_linear or t.D != self.D:
            return self.box
        return t.policy.init_bounds(t.n_s, t.n_a, self.box)


@dataclass(frozen=True)
class RawGuess:
    """An attack's reading of the raw values behind one shown entry: the entry as printed
    (``params`` encoded, shape (D,), with their printed ``tols``; ``ret`` the printed encoded
    return) and the raw return (reward units) and raw parameters the attack decodes for it."""

    params: tuple[float, ...]
    tols: tuple[float, ...]
    ret: float
    raw_ret: float
    raw_params: tuple[float, ...]


@dataclass(frozen=True)
class Estimate:
    """What an attack found: an estimate of ``target`` ("c": a float; "a": shape (D,), NaN where not
    estimated), or ``value=None`` when it found nothing; ``detail`` says how, without secret values.
    """

    attack: str
    target: str  # "c" or "a"
    value: float | np.ndarray | None  # None: the attack found nothing; a: NaN where not estimated
    detail: str = ""
    extras: dict[str, float] = field(default_factory=dict)  # other secrets it estimated (s, p)
    # why the attack could not run at all (env private, a fact unknown, initial states unknown, over
    # its budget); empty when it ran (then value None means it ran and found nothing)
    not_run: str = ""
    raw: tuple[RawGuess, ...] = ()  # raw values it decodes for shown entries (simulator attacks)

    @property
    def applicable(self) -> bool:
        """True when the estimate holds at least one finite value."""
        if self.value is None:
            return False
        return bool(np.any(np.isfinite(np.atleast_1d(self.value))))


def view_of(requests: Sequence[Request], task: str | Task, box: tuple[float, float]) -> View:
    """The provider's view of one transcript: the distinct history entries shown (parsed from the
    request bodies), the warm-up entries, and the task's public facts. ``task``: its name, or the
    Task itself (its public declaration: what a simulator attack needs to build a public env).
    """
    seen: dict[tuple[tuple[str, ...], str], Shown] = {}
    first: list[Shown] = []
    D = 0
    for k, r in enumerate(requests):
        for e in r.entries:
            parsed = [token_value(t) for t in e.params]
            ret = token_value(e.ret)
            if ret is None or any(p is None for p in parsed) or not parsed:
                continue
            D = max(D, len(parsed))
            key = (e.params, e.ret)
            if key not in seen:
                seen[key] = Shown(np.array([p[0] for p in parsed if p]), np.array([p[1] for p in parsed if p]),
                                  ret[0], ret[1], dict(e.diagnostics), k, tuple(e.components))
            if k == 0:
                first.append(seen[key])
    entries = tuple(s for s in seen.values() if len(s.params) == D)
    grid = bool(entries) and all(_INTEGER.fullmatch(t) for r in requests for e in r.entries for t in e.params)
    return View(tuple(requests), entries, tuple(s for s in first if len(s.params) == D), facts_for(task), box, D,
                task=None if isinstance(task, str) else task, grid=grid)



def same_marker(printed: str | None, marker: str) -> bool:
    """True when a printed diagnostic equals ``marker`` (as text, or as the same number)."""
    if printed is None:
        return False
    if printed == marker:
        return True
    a, b = token_value(printed), token_value(marker)
    return a is not None and b is not None and a[0] == b[0]
