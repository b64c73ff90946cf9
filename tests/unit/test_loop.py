"""Unit tests of ppprops.loop: ``locate`` (which phase asks for candidate i) and ``best_candidate``.

The loop itself is the study's (tests/test_study.py drives it by hand with a scripted proposer).
"""

from __future__ import annotations

import numpy as np
import pytest

from ppprops.client.codec import Codec
from ppprops.client.secrets import Secrets
from ppprops.loop import Phase, best_candidate, locate
from ppprops.proposers.base import Proposal, StopSearch
from ppprops.values import Candidate, Feedback

A = np.array([2.0, 0.5, 4.0])  # the secret parameter scales a_j
C = 3.0  # the secret reward scale c


class Scripted:
    """Proposes ``base + iteration`` in every coordinate; remembers every ask and every tell."""

    def __init__(self, base: float, source: str, stop_at: int | None = None) -> None:
        self.base, self.source, self.stop_at = base, source, stop_at
        self.asked: list[int] = []
        self.told: list[int] = []

    def ask(self, iteration: int) -> Proposal:
        if iteration == self.stop_at:
            raise StopSearch("scripted stop")
        self.asked.append(iteration)
        return Proposal(np.full(3, self.base + iteration), self.source, clipped=iteration % 2, note=f"it{iteration}")

    def tell(self, candidate: Candidate) -> None:
        self.told.append(candidate.index)


def evaluate(theta: np.ndarray, index: int) -> tuple[Feedback, list[int]]:
    """Return -(sum theta)^2 (a known number), one component, episode seeds 100 * index + (0, 1)."""
    ret = -float(np.sum(theta)) ** 2
    return Feedback(ret=ret, components={"alive": 1.0}, diagnostics={"steps": 7.0}, episode_returns=(ret, ret)), [100 * index, 100 * index + 1]


@pytest.fixture
def codec() -> Codec:
    return Codec(Secrets(run_id="loop", a=A, c=C), encode_params=True, scale_rewards=True)


def test_locate_maps_each_index_to_its_phase_and_local_iteration() -> None:
    w, s, t = Phase("warmup", Scripted(0, "w"), 3), Phase("search", Scripted(0, "s"), 2), Phase("tail", Scripted(0, "t"), 1)
    expected = [(w, 0), (w, 1), (w, 2), (s, 0), (s, 1), (t, 0)]
    assert [locate([w, s, t], i) for i in range(6)] == expected
    with pytest.raises(IndexError, match="candidate 6 is past the run's budget of 6"):
        locate([w, s, t], 6)


def test_locate_skips_empty_phases() -> None:
    w, empty, s = Phase("warmup", Scripted(0, "w"), 2), Phase("none", Scripted(0, "n"), 0), Phase("search", Scripted(0, "s"), 2)
    assert locate([w, empty, s], 2) == (s, 0)


def test_best_candidate_skips_non_finite_returns_and_keeps_the_earliest_tie() -> None:
    def fb(ret: float) -> Feedback:
        return Feedback(ret=ret)

    def cand(i: int, ret: float) -> Candidate:
        return Candidate(index=i, iteration=i, source="x", params=np.zeros(1), params_enc=np.zeros(1),
                         feedback=fb(ret), feedback_enc=fb(ret), clipped=0, seeds=())  # fmt: skip

    assert best_candidate([cand(0, 1.0), cand(1, float("nan")), cand(2, 5.0), cand(3, 5.0), cand(4, float("inf"))]).index == 2
    assert best_candidate([cand(0, float("nan")), cand(1, float("nan"))]).index == 0
    with pytest.raises(ValueError, match="no candidates"):
        best_candidate([])
