"""Unit tests of the one search loop (ppprops.loop): ``locate`` and ``run_loop``.

A scripted proposer stands in for the LLM and a closed-form evaluator for the environment, so
every recorded value can be computed independently here: which vector was evaluated at which
index, what the store holds raw and encoded, and what each proposer was told.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ppprops.client.codec import Codec
from ppprops.client.secrets import Secrets
from ppprops.loop import Phase, best_candidate, locate, run_loop
from ppprops.proposers.base import Proposal, StopSearch
from ppprops.store import open_store
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


def test_run_loop_evaluates_records_and_tells_in_order(tmp_path: Path, codec: Codec) -> None:
    warm, search = Scripted(0.0, "warmup"), Scripted(10.0, "llm")
    seen: list[int] = []
    with open_store(tmp_path, create=True) as store:
        out = run_loop([Phase("warmup", warm, 2), Phase("llm", search, 3)], evaluate=evaluate, codec=codec, store=store,
                       on_candidate=lambda c: seen.append(c.index))  # fmt: skip
        stored = store.candidates()
    assert [c.index for c in out] == [0, 1, 2, 3, 4] == seen
    assert [(c.source, c.iteration) for c in out] == [("warmup", 0), ("warmup", 1), ("llm", 0), ("llm", 1), ("llm", 2)]
    assert warm.asked == [0, 1] and search.asked == [0, 1, 2]
    assert warm.told == search.told == [0, 1, 2, 3, 4]  # every proposer hears every candidate
    raw = [0.0, 1.0, 10.0, 11.0, 12.0]
    for c, r, s in zip(out, raw, stored, strict=True):
        assert np.array_equal(c.params, np.full(3, r))
        assert np.allclose(c.params_enc, A * r)  # theta~ = A theta (Eq. 5)
        assert c.ret == -(3 * r) ** 2
        assert c.feedback_enc.ret == pytest.approx(C * c.ret)  # r~ = c r (Eq. 7)
        assert c.feedback_enc.components == {"alive": pytest.approx(C)}
        assert c.seeds == (100 * c.index, 100 * c.index + 1)
        assert (c.clipped, c.note) == (c.iteration % 2, f"it{c.iteration}")
        assert (s.index, s.source, s.ret, s.seeds) == (c.index, c.source, c.ret, c.seeds)
        assert np.array_equal(s.params, c.params) and np.allclose(s.params_enc, c.params_enc)
    assert best_candidate(out).index == 0  # -(3 * 0)^2 = 0 is the highest return


def test_run_loop_resumes_from_done_candidates(tmp_path: Path, codec: Codec) -> None:
    """A resumed run replays ``done`` into the proposers and asks only for the missing indices."""
    (tmp_path / "first").mkdir()
    (tmp_path / "second").mkdir()
    with open_store(tmp_path / "first", create=True) as store:
        first = run_loop([Phase("warmup", Scripted(0.0, "warmup"), 2), Phase("llm", Scripted(10.0, "llm"), 3)],
                         evaluate=evaluate, codec=codec, store=store)  # fmt: skip
    warm, search = Scripted(0.0, "warmup"), Scripted(10.0, "llm")
    calls: list[int] = []

    def counting(theta: np.ndarray, index: int) -> tuple[Feedback, list[int]]:
        calls.append(index)
        return evaluate(theta, index)

    with open_store(tmp_path / "second", create=True) as store:
        out = run_loop([Phase("warmup", warm, 2), Phase("llm", search, 3)], evaluate=counting, codec=codec, store=store,
                       done=first[:3])  # fmt: skip
        assert [c.index for c in store.candidates()] == [3, 4]  # only the new ones are written
    assert calls == [3, 4]
    assert warm.asked == [] and search.asked == [1, 2]  # the interrupted iteration is asked again, by its number
    assert search.told == [0, 1, 2, 3, 4]
    assert [c.ret for c in out] == [c.ret for c in first]


def test_stop_search_leaves_the_recorded_candidates(tmp_path: Path, codec: Codec) -> None:
    with open_store(tmp_path, create=True) as store:
        with pytest.raises(StopSearch, match="scripted stop"):
            run_loop([Phase("warmup", Scripted(0.0, "warmup"), 2), Phase("llm", Scripted(10.0, "llm", stop_at=1), 3)],
                     evaluate=evaluate, codec=codec, store=store)  # fmt: skip
        assert [(c.index, c.source) for c in store.candidates()] == [(0, "warmup"), (1, "warmup"), (2, "llm")]


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
