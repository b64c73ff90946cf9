"""The selection stage: the search's top candidates run again on fresh episodes before one is handed over.

With one episode per candidate the best search-time return is the luckiest of many noisy draws,
not the best policy (the winner's curse). After the search, ``SelectionProposer`` asks the top
``budget`` candidates by search-time mean return once more each, on ``episodes`` fresh episode
seeds of their own (``seeding.SELECTION``, never used by the search or the final evaluation);
``loop.select_best`` then hands over the one with the best mean over all its episodes. Nothing of
this stage reaches a prompt: the search is over.
"""

from __future__ import annotations

import math

from .. import seeding
from ..values import Candidate
from .base import Proposal, SearchProposer


class SelectionProposer(SearchProposer):
    """Ask ``i`` re-evaluates the search candidate ranked ``i`` by search-time mean return (finite
    returns only, the earliest first on a tie; past the last one, the best again), on ``episodes``
    seeds drawn from ``streams``. ``stage`` numbers the selection stages of a run (0; 1 and on for
    a search continued after one, ``phases.plan_phases``): each stage draws seeds of its own."""

    def __init__(self, streams: seeding.Streams, episodes: int, stage: int = 0) -> None:
        self.streams = streams
        self.episodes = episodes
        self.stage = stage
        self._search: list[Candidate] = []

    def tell(self, candidate: Candidate) -> None:
        """Search candidates are ranked; re-evaluations are not."""
        if candidate.reevaluates is None:
            self._search.append(candidate)

    def ranking(self) -> list[Candidate]:
        """The search candidates with a finite return, best first (the earliest first on a tie)."""
        finite = [c for c in self._search if math.isfinite(c.ret)]
        return sorted(finite, key=lambda c: (-c.ret, c.index))

    def ask(self, iteration: int) -> Proposal:
        """Re-evaluate the candidate ranked ``iteration``: its own parameters, fresh seeds (its own
        stream; a repeat of the best, when fewer candidates than asks, on yet other seeds)."""
        ranked = self.ranking() or self._search
        if not ranked:
            raise RuntimeError("the selection stage follows the search: no candidate was told")
        repeat, rank = divmod(iteration, len(ranked))
        c = ranked[rank] if repeat == 0 else ranked[0]
        key = (c.index if repeat == 0 else c.index + (repeat << 32)) + (self.stage << 48)
        words = self.streams.rng(seeding.SELECTION, key).integers(0, 2**32, size=self.episodes, dtype="uint64")
        return Proposal(theta=c.params.copy(), source="reeval", note=f"re-evaluates candidate {c.index}",
                        seeds=tuple(int(w) for w in words), reevaluates=c.index)
