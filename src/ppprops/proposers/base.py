"""The ask/tell protocol every proposer implements, and how a proposer stops a search."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from ..values import Candidate


class StopSearch(Exception):
    """Raised by a proposer's ``ask`` when it cannot go on (e.g. its prompt no longer fits the
    context window). The run stops there (status ``stopped: <reason>``) and reports the best
    policy found before it; ``reason`` is that one line."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class Proposal:
    """One proposed policy: raw theta, shape (D,), inside the box, and where it came from."""

    theta: np.ndarray  # raw parameters, already inside the feasible box
    source: str  # recorded as the candidate's source: warmup, llm, fallback, random, ...
    clipped: int = 0  # coordinates that had to be clipped into the box
    note: str = ""


class Proposer(Protocol):
    """The ask/tell interface of every search (warm-up sampler, LLM, R2PO, random, CMA-ES).

    ``ask`` may raise StopSearch to end the run on purpose; the loop (``ppprops.loop.run_loop``)
    evaluates and records each proposal and tells every proposer every candidate.
    """

    def ask(self, iteration: int) -> Proposal:
        """The next candidate. ``iteration`` counts this proposer's own asks from 0, so a
        resumed run asks again for exactly the iteration that was interrupted."""
        ...

    def tell(self, candidate: Candidate) -> None:
        """Every evaluated candidate of the run, in order (including other proposers')."""
        ...


def clip_to_box(theta: np.ndarray, box: tuple[float, float]) -> tuple[np.ndarray, int]:
    """``theta`` (shape (D,)) clipped into ``box`` = (low, high), and how many coordinates were outside."""
    lo, hi = box
    clipped = int(np.count_nonzero((theta < lo) | (theta > hi)))
    return np.clip(theta, lo, hi), clipped
