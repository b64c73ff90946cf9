"""The request pacer (``llm.pacing.Pacer``) with a fake clock, and the timing measurement
(``privacy.timing``) on planted request times: no sleeping, no model."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from ppprops.llm.pacing import Pacer
from ppprops.privacy import timing
from ppprops.values import Candidate, Feedback


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0
        self.slept: list[float] = []

    def sleep(self, s: float) -> None:
        self.slept.append(s)
        self.now += s


class State:
    def __init__(self) -> None:
        self.state: dict[str, Any] = {}

    def pacing_state(self) -> dict[str, Any]:
        return dict(self.state)

    def set_pacing_state(self, state: Any) -> None:
        self.state = dict(state)


def _gaps(evals: list[float], floor: float = 0.0, jitter: float = 0.0) -> list[float]:
    """The gaps a provider sees (answer -> next request) when the client needs ``evals`` seconds each time."""
    clock, state = Clock(), State()
    pacer = Pacer(state, lambda n: np.random.default_rng(n), floor=lambda: floor, jitter=jitter, clock=lambda: clock.now,
                  sleep=clock.sleep)
    pacer.before_request()  # the first request: nothing to pace
    pacer.answered()
    seen = []
    for e in evals:
        answered_at = clock.now
        clock.now += e  # evaluate, tell, ask
        pacer.before_request()
        seen.append(clock.now - answered_at)
        pacer.answered()
    return seen


def test_every_gap_below_the_pad_leaves_at_the_pad() -> None:
    gaps = _gaps([0.1, 0.3, 0.2, 0.05, 0.25], floor=0.3)
    assert np.allclose(gaps, [0.6] * 5)  # 2 x the floor (the longest warm-up gap), whatever the evaluation took


def test_a_gap_longer_than_the_pad_leaves_as_it_is_and_raises_the_pad() -> None:
    gaps = _gaps([0.1, 0.9, 0.2, 0.3], floor=0.3)
    assert np.allclose(gaps, [0.6, 0.9, 1.8, 1.8])


def test_a_pause_leaves_as_it_is_and_leaves_the_pad_alone() -> None:
    # 894 s: a run resumed a quarter of an hour after its process died (a gap of more than PAUSE pads)
    gaps = _gaps([0.1, 894.0, 0.2, 0.3], floor=0.3)
    assert np.allclose(gaps, [0.6, 894.0, 0.6, 0.6])  # not 1788 s for every request after it
    gaps = _gaps([0.1, 5.9, 0.2], floor=0.3)  # 5.9 s < PAUSE x 0.6 s: an evaluation longer than ever, which raises the pad
    assert np.allclose(gaps, [0.6, 5.9, 11.8])


def test_restart_lets_a_new_loop_send_its_first_request_at_once() -> None:
    clock, state = Clock(), State()
    pacer = Pacer(state, lambda n: np.random.default_rng(n), floor=lambda: 0.5, jitter=0.0, clock=lambda: clock.now, sleep=clock.sleep)
    pacer.before_request()
    pacer.answered()
    clock.now += 3.0  # the process dies; resume starts another three seconds later
    again = Pacer(state, lambda n: np.random.default_rng(n), floor=lambda: 0.5, jitter=0.0, clock=lambda: clock.now, sleep=clock.sleep)
    again.restart()
    assert again.before_request() == 0.0 and state.state.get("longest_gap", 0.0) == 0.0 and state.state["requests"] == 2
    again.answered()
    clock.now += 0.1
    assert again.before_request() == pytest.approx(0.9)  # then paced as before: 2 x the floor
    assert clock.slept == [pytest.approx(0.9)]


def test_the_jitter_is_drawn_per_request_from_the_keyed_stream() -> None:
    gaps = _gaps([0.1] * 4, floor=0.5, jitter=0.25)
    want = [1.0 + 0.25 * 1.0 * np.random.default_rng(n).uniform() for n in range(1, 5)]
    assert np.allclose(gaps, want) and len(set(np.round(gaps, 9))) == 4


def _cand(i: int, ret: float) -> Candidate:
    fb = Feedback(ret=ret, diagnostics={"episode_length": ret})
    return Candidate(index=i, iteration=i, source="llm", params=np.zeros(2), params_enc=np.zeros(2), feedback=fb,
                     feedback_enc=Feedback(ret=2.0 * ret), clipped=0, seeds=(i,))


def _planted(gap_of: Any) -> tuple[list[dict[str, Any]], list[tuple[float, Candidate]]]:
    """Ten requests; between the answer of one and the next, one candidate told, the gap ``gap_of(return)``."""
    rets = [30.0, 120.0, 60.0, 200.0, 15.0, 90.0, 150.0, 45.0, 180.0]
    calls, told, t = [], [], 0.0
    for k in range(10):
        calls.append({"sent": t, "latency_s": 0.5, "ok": True, "answered": True, "retry": 0})
        t += 0.5
        if k < len(rets):
            g = gap_of(rets[k])
            told.append((t + 0.9 * g, _cand(k, rets[k])))
            t += g
    return calls, told


def test_a_planted_correlation_is_measured_and_calibrated() -> None:
    calls, told = _planted(lambda r: 0.01 + 0.002 * r)
    got = timing.measure(calls, told, [k.index for _, k in told], c=2.0, pure_scale=True)
    assert isinstance(got, timing.Timing)
    assert got.rho_steps == 1.0 and got.rho_return == 1.0 and got.significant
    assert got.best_error is not None and got.best_error < 1e-9 and got.c_error is not None and got.c_error < 1e-9
    assert got.prior_c_error == 1.0  # c = 1 against 2


def test_constant_gaps_show_nothing() -> None:
    calls, told = _planted(lambda r: 0.5)
    got = timing.measure(calls, told, [k.index for _, k in told])
    assert isinstance(got, timing.Timing) and got.rho_steps == 0.0 and not got.significant


def test_too_few_gaps_are_not_measured() -> None:
    calls, told = _planted(lambda r: r)
    assert timing.measure(calls[:4], told[:3], []) == "3 gaps between an answer and the next request (needs 6)"


def _rounds(serial: bool) -> tuple[list[dict[str, Any]], list[tuple[float, Candidate]], list[list[float]]]:
    """Ten rounds of --parallel 3: three requests leave together (1 ms apart), their trials are
    told, and the next round leaves when the last is: after the longest (side by side) or the sum
    (one after another) of the round's episodes, at 2 ms per step."""
    rounds = [[30.0, 120.0, 20.0], [60.0, 15.0, 10.0], [200.0, 40.0, 35.0], [90.0, 100.0, 6.0],
              [150.0, 10.0, 12.0], [45.0, 20.0, 8.0], [180.0, 190.0, 7.0], [70.0, 60.0, 65.0], [110.0, 5.0, 5.0],
              [25.0, 25.0, 25.0]]
    calls, told, t, i = [], [], 0.0, 0
    for rets in rounds:
        for k in range(3):
            calls.append({"sent": t + 0.001 * k, "latency_s": 0.5, "ok": True, "answered": True, "retry": 0})
        t += 0.502
        ends = np.cumsum([0.002 * x for x in rets]) if serial else [0.002 * x for x in rets]
        for ret, end in zip(rets, ends, strict=True):
            told.append((t + float(end), _cand(i, ret)))
            i += 1
        t += float(max(ends)) + 0.01
    return calls, told, rounds


@pytest.mark.parametrize("serial", [False, True])
def test_a_round_gives_one_gap_that_follows_its_longest_or_summed_trials(serial: bool) -> None:
    calls, told, rounds = _rounds(serial)
    got = timing.pairs(calls, told, width=3)
    assert [[k.index for k in batch] for _, batch in got] == [[3 * r, 3 * r + 1, 3 * r + 2] for r in range(9)]  # the last round has no next
    got_t = timing.measure(calls, told, [k.index for _, k in told], width=3)
    assert isinstance(got_t, timing.Timing) and got_t.rho_steps == 1.0 and got_t.significant
    combine = sum if serial else max
    assert got_t.steps == [combine(r) for r in rounds[:-1]]
    assert got_t.returns == [max(r) for r in rounds[:-1]]  # scored against the round's best raw return
    assert timing.pairs(calls, told, width=1) == []  # a width-1 reading of the same run sees no one-candidate gap
