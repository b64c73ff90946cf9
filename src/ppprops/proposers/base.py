"""The ask/tell protocol every proposer implements."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from ..store import Candidate


@dataclass(frozen=True)
class Proposal:
    theta: np.ndarray  # raw parameters, already inside the feasible box
    source: str  # recorded as the candidate's source: warmup, llm, fallback, random, ...
    clipped: int = 0  # coordinates that had to be clipped into the box
    note: str = ""


class Proposer(Protocol):
    def ask(self, iteration: int) -> Proposal:
        """The next candidate. ``iteration`` counts this proposer's own asks from 0, so a
        resumed run asks again for exactly the iteration that was interrupted."""
        ...

    def tell(self, candidate: Candidate) -> None:
        """Every evaluated candidate of the run, in order (including other proposers')."""
        ...


def clip_to_box(theta: np.ndarray, box: tuple[float, float]) -> tuple[np.ndarray, int]:
    lo, hi = box
    clipped = int(np.count_nonzero((theta < lo) | (theta > hi)))
    return np.clip(theta, lo, hi), clipped
