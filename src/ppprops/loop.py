"""Where a candidate belongs in a search, and which candidate is the best (the one handed over).

A search is a sequence of phases (for PP-ProPS: warm-up, then LLM iterations; ``proposers.base.Phase``).
Each candidate index belongs to exactly one (phase, iteration), so a study (``ppprops.study``)
knows where to continue from the number of recorded candidates alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .values import Candidate

if TYPE_CHECKING:  # the phases' module loads with the proposers: picking the best needs neither
    from .proposers.base import Phase

__all__ = ["Phase", "best_candidate", "locate", "pooled_returns", "select_best", "search_candidates"]


def __getattr__(name: str) -> Any:
    if name == "Phase":  # re-exported (``from ppprops.loop import Phase``)
        from .proposers.base import Phase

        return Phase
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def locate(phases: Sequence[Phase], index: int) -> tuple[Phase, int]:
    """The phase and the proposer's iteration that produce candidate ``index`` (0-based).

    Phases are laid end to end: phase k holds indices [sum of earlier budgets, + its budget), asked
    as its proposer's iterations from ``Phase.offset``. Raises IndexError for an index at or past
    the total budget.
    """
    start = 0
    for ph in phases:
        if index < start + ph.budget:
            return ph, ph.offset + index - start
        start += ph.budget
    raise IndexError(f"candidate {index} is past the run's budget of {start}")


def best_candidate(candidates: Sequence[Candidate]) -> Candidate:
    """Highest finite raw return; the earliest wins a tie (Algorithm 1 updates on strict
    improvement). A NaN or infinite return (a numerical fault) is never the best; if no return
    is finite, the first candidate. Raises ValueError for an empty sequence."""
    if not candidates:
        raise ValueError("no candidates")
    finite = [c for c in candidates if math.isfinite(c.ret)]
    if not finite:
        return candidates[0]
    best = finite[0]
    for c in finite[1:]:
        if c.ret > best.ret:
            best = c
    return best


def search_candidates(candidates: Sequence[Candidate]) -> list[Candidate]:
    """The candidates of the search itself: every one but the selection stage's re-evaluations."""
    return [c for c in candidates if c.reevaluates is None]


def pooled_returns(candidates: Sequence[Candidate]) -> dict[int, tuple[float, ...]]:
    """For each search candidate that was re-evaluated: every episode return it has, those of the
    search and those of its re-evaluations (raw reward units), by its index."""
    by_index = {c.index: c for c in candidates}
    pooled: dict[int, list[float]] = {}
    for r in candidates:
        if r.reevaluates is None or r.reevaluates not in by_index:
            continue
        if r.reevaluates not in pooled:
            own = by_index[r.reevaluates].feedback
            pooled[r.reevaluates] = list(own.episode_returns) or [own.ret]
        pooled[r.reevaluates] += list(r.feedback.episode_returns) or [r.ret]
    return {k: tuple(v) for k, v in pooled.items()}


def select_best(candidates: Sequence[Candidate]) -> Candidate:
    """The candidate handed over (the policy file, the final evaluation, ``SearchResult.best``).

    Without re-evaluations: ``best_candidate`` of the search's candidates (Algorithm 1's
    ``theta_best``). After the selection stage (the top candidates of the search run again on fresh
    episodes): the re-evaluated search candidate with the highest mean over all its episodes,
    search and re-evaluation pooled, so one lucky episode cannot win on its own; the earliest wins
    a tie, and a non-finite mean never does. Raises ValueError for an empty sequence.
    """
    search = search_candidates(candidates)
    if not search:
        raise ValueError("no candidates")
    pooled = pooled_returns(candidates)
    means = {i: float(np.mean(v)) for i, v in pooled.items() if v and all(math.isfinite(r) for r in v)}
    if not means:
        return best_candidate(search)
    top = max(means.values())
    index = min(i for i, m in means.items() if m == top)
    return next(c for c in search if c.index == index)
