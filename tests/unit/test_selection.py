"""The selection stage (``ppprops.proposers.selection``) and who is handed over (``ppprops.loop``);
the stall count of the LLM proposer, which the audit recounts (``ppprops.proposers.llm``)."""

from __future__ import annotations

import numpy as np
import pytest

from ppprops.loop import pooled_returns, select_best
from ppprops.proposers.llm import StallCounter, stall_count
from ppprops.proposers.selection import SelectionProposer
from ppprops.seeding import Streams
from ppprops.values import Candidate, Feedback


def cand(i: int, ret: float, source: str = "llm", reevaluates: int | None = None, episodes: tuple[float, ...] = ()) -> Candidate:
    fb = Feedback(ret=ret, episode_returns=episodes or (ret,))
    return Candidate(i, i, source, np.full(3, float(i)), np.full(3, float(i)), fb, fb, 0, (i,), reevaluates=reevaluates)


def test_the_top_candidates_are_asked_again_best_first_on_fresh_seeds_of_their_own() -> None:
    stage = SelectionProposer(Streams(0, b"k" * 32), episodes=4)
    for c in (cand(0, 10.0, "warmup"), cand(1, 30.0), cand(2, float("nan")), cand(3, 30.0), cand(4, 20.0)):
        stage.tell(c)
    asks = [stage.ask(i) for i in range(3)]
    assert [a.reevaluates for a in asks] == [1, 3, 4]  # best first, the earliest on a tie, no NaN
    assert all(a.source == "reeval" and len(a.seeds or ()) == 4 for a in asks)
    assert len({a.seeds for a in asks}) == 3
    np.testing.assert_array_equal(asks[0].theta, np.full(3, 1.0))
    again = SelectionProposer(Streams(0, b"k" * 32), episodes=4)
    for c in (cand(1, 30.0), cand(3, 30.0)):
        again.tell(c)
    assert again.ask(0).seeds == asks[0].seeds  # keyed: the same key gives the same seeds
    assert again.ask(2).reevaluates == 1 and again.ask(2).seeds not in (asks[0].seeds, again.ask(0).seeds)  # a repeat: other seeds


def test_the_candidate_with_the_best_pooled_mean_is_handed_over_not_the_luckiest_episode() -> None:
    lucky, steady = cand(0, 500.0), cand(1, 400.0)
    reevals = [cand(2, 100.0, "reeval", reevaluates=0, episodes=(100.0, 120.0)), cand(3, 410.0, "reeval", reevaluates=1, episodes=(410.0, 390.0))]
    assert pooled_returns([lucky, steady, *reevals]) == {0: (500.0, 100.0, 120.0), 1: (400.0, 410.0, 390.0)}
    assert select_best([lucky, steady, *reevals]).index == 1
    assert select_best([lucky, steady]).index == 0  # without re-evaluations: the best search-time return


def test_the_stall_count_is_one_count_for_the_proposer_and_the_audit() -> None:
    history = [cand(0, 5.0, "warmup"), cand(1, 4.0), cand(2, 6.0), cand(3, 6.0), cand(4, float("nan"), "fallback"), cand(5, 1.0)]
    counter = StallCounter()
    counts = []
    for c in history:
        counter.tell(c)
        counts.append(counter.count)
    assert counts == [0, 1, 0, 1, 2, 3]
    assert [stall_count(history[: i + 1]) for i in range(len(history))] == counts


def test_the_selection_stage_needs_a_search_to_follow() -> None:
    with pytest.raises(RuntimeError, match="follows the search"):
        SelectionProposer(Streams(0), episodes=2).ask(0)
