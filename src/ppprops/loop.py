"""Where a candidate belongs in a search, and which candidate is the best.

A search is a sequence of phases (for PP-ProPS: warm-up, then LLM iterations; ``proposers.base.Phase``).
Each candidate index belongs to exactly one (phase, iteration), so a study (``ppprops.study``)
knows where to continue from the number of recorded candidates alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from .proposers.base import Phase
from .values import Candidate

__all__ = ["Phase", "best_candidate", "locate"]


def locate(phases: Sequence[Phase], index: int) -> tuple[Phase, int]:
    """The phase and the phase-local iteration that produce candidate ``index`` (0-based).

    Phases are laid end to end: phase k holds indices [sum of earlier budgets, + its budget).
    Raises IndexError for an index at or past the total budget.
    """
    start = 0
    for ph in phases:
        if index < start + ph.budget:
            return ph, index - start
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
