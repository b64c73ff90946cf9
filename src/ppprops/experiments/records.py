"""What the report reads of each run (``RunRecord``) and how runs are grouped into table cells (``Group``).

Kept apart from the tables (``experiments.report``) and the figures (``experiments.plots``), which
both read these records.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..methods import MethodKind, find_method
from ..status import RunKind, is_complete
from . import paper_values as pv
from .order import DEFAULT_K


def method_kind(method: str, kind: str) -> MethodKind:
    """A run's method kind from the registry; a search method this version does not know counts as prompted."""
    m = find_method(method)
    if m is not None:
        return m.kind
    return MethodKind.RL if kind == RunKind.RL else MethodKind.PROMPTED


@dataclass
class RunRecord:
    """What the report needs of one run."""

    name: str
    path: Path
    kind: RunKind
    task: str
    method: str
    top_k: int | None
    seed: int
    status: str
    best: float | None
    final: float | None
    warmup: int = 0
    D: int | None = None
    returns: list[float | None] = field(default_factory=list)  # candidate returns, by index
    calls: list[dict[str, Any]] = field(default_factory=list)  # LLM calls (iteration, latency_s, prompt_chars, ok)

    @property
    def done(self) -> bool:
        """True when the run is finished or stopped on purpose (it counts in the tables)."""
        return is_complete(self.status, self.kind)

    @property
    def column(self) -> str:
        """Its table column (``column_name``)."""
        return column_name(self.method, self.top_k, self.kind)

    @property
    def score(self) -> float | None:
        """The number a table compares: the search-time best; an RL run's final evaluation."""
        return self.final if self.kind == RunKind.RL else self.best


def column_name(method: str, top_k: int | None, kind: str) -> str:
    """A table column: the method, with the history bound when a prompted method ran with K != 10."""
    if method_kind(method, kind) is not MethodKind.PROMPTED or top_k in (None, DEFAULT_K):
        return method
    return f"{method} (unbounded)" if top_k == 0 else f"{method} (K={top_k})"




# -- reading ---------------------------------------------------------------------------------
def read_run(path: Path) -> RunRecord:
    """The RunRecord of the run directory ``path`` (opened with ``rundir.open_run``), read through
    the run summary (``ppprops.summary``).

    Returns are raw reward units. ``D`` is None when the task's size cannot be known (neither a
    stored task declaration nor a task of that name).

    Raises:
        StoreError: ``path`` holds no readable run.
    """
    from ..rundir import open_run
    from ..summary import summarize

    with open_run(path) as run:
        s = summarize(run)
        kind = run.kind
    cfg = s["config"]
    fe = s.get("final_eval")
    rec = RunRecord(
        name=path.name, path=path, kind=kind, task=str(s["env"]), method=str(s["method"]),
        top_k=None if kind == RunKind.RL else int(cfg.get("top_k", DEFAULT_K)), seed=int(s["seed"]), status=str(s["status"]),
        best=_search_best(s) if kind == RunKind.SEARCH else None, final=fe["mean"] if fe else None,
        warmup=int(cfg.get("warmup", 0)) if kind == RunKind.SEARCH else 0,
        returns=[c["return"] for c in s["candidates"] if c.get("reevaluates") is None],  # the search, not the selection stage
        calls=[{k: c[k] for k in ("iteration", "latency_s", "prompt_chars", "ok")} for c in s["llm_calls"]],
    )  # fmt: skip
    spec = cfg.get("task_spec")
    try:
        from ..tasks import get_task

        rec.D = (len(spec["observation"]["names"]) + 1) * len(spec["actions"]) if spec else get_task(rec.task).D
    except (ConfigError, KeyError, TypeError):
        rec.D = None
    return rec


def _search_best(s: dict[str, Any]) -> float | None:
    """The best single return of the search (the paper's number, Algorithm 1's theta_best), whichever
    candidate the selection stage handed over."""
    best = s.get("best") or {}
    first = best.get("search_best") or best
    return first.get("return")


# -- aggregation -----------------------------------------------------------------------------
def _mean_std(values: Sequence[float | None]) -> tuple[float | None, float | None, int]:
    xs = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not xs:
        return None, None, 0
    return float(np.mean(xs)), float(np.std(xs)), len(xs)


@dataclass
class Group:
    """The finished runs of one (task, column): the seeds of one cell of a table."""

    task: str
    column: str
    method: str
    top_k: int | None
    kind: RunKind
    runs: list[RunRecord]

    @property
    def method_kind(self) -> MethodKind:
        """The group's method kind (``method_kind``): prompted, black-box or RL."""
        return method_kind(self.method, self.kind)

    def stats(self) -> dict[str, Any]:
        """Mean and population std over the group's runs (finite values only), and the paper's number.

        Keys: task, column, method, top_k, kind, n (runs), seeds, ``score_*`` (what tables compare:
        the search-time best; RL: the final evaluation), ``best_*``, ``final_*`` (None when no run
        has one), ``paper_mean``, ``paper_std``, ``paper_table``, ``paper_note`` (``paper_values``).
        """
        bm, bs, bn = _mean_std([r.best for r in self.runs])
        fm, fs, fn = _mean_std([r.final for r in self.runs])
        sm, ss, sn = _mean_std([r.score for r in self.runs])
        ref = pv.main_value(self.task, self.method, self.top_k if self.top_k is not None else DEFAULT_K)
        return {"task": self.task, "column": self.column, "method": self.method, "top_k": self.top_k, "kind": self.kind,
                "n": len(self.runs), "seeds": sorted(r.seed for r in self.runs), "score_mean": sm, "score_std": ss,
                "best_mean": bm, "best_std": bs, "final_mean": fm, "final_std": fs,
                "paper_mean": ref.mean if ref else None, "paper_std": ref.std if ref else None,
                "paper_table": ref.table if ref else None, "paper_note": ref.note if ref else None}  # fmt: skip


def group_runs(runs: Sequence[RunRecord]) -> dict[tuple[str, str], Group]:
    """The finished runs by (task, column); unfinished runs are left out."""
    groups: dict[tuple[str, str], Group] = {}
    for r in runs:
        if not r.done:
            continue
        g = groups.setdefault((r.task, r.column), Group(r.task, r.column, r.method, r.top_k, r.kind, []))
        g.runs.append(r)
    return groups
