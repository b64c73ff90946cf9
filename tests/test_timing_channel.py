"""The provider's clock: on a rig stepped in real time, the gap between an answer and the next
request follows the episode the client just ran. The audit measures it on the run's recorded
request times (``privacy.timing``) and reports it; with ``pace_requests`` (``llm.pacing``) the gaps
no longer follow the episodes and the audit finds nothing. Driven through ask/tell with the
offline stand-in optimizer, each trial's evaluation 2 ms per step on a virtual clock
(``support.VirtualClock``: the store's stamps and the pacer's waits read it), so that the gaps the
audit measures are the same on every run of a test, whatever the load of the machine."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

import ppprops
from ppprops import seeding
from ppprops.privacy.audit import audit_run
from ppprops.privacy.matrix import analyse_run, format_report
from ppprops.privacy.timing import spearman
from ppprops.store import open_store
from ppprops.study import StudyComplete

from support import VirtualClock, offline_llm

STEP_S = 0.002
WARMUP = [40, 200, 90]  # the warm-up's episode lengths: random policies span the range
SEARCH = [int(x) for x in np.random.default_rng(0).permutation(np.linspace(10, 190, 14)).round()]
# --parallel 4: each round's four trials are held by four workers at once and the round's requests
# leave when the last is told; one long trial per round (its length a permutation of the range), three
# short ones
ROUND_LONGEST = [int(x) for x in np.random.default_rng(1).permutation(np.linspace(20, 190, 12)).round()]
WIDE_WARMUP = [40, 200, 90, 150]
JITTER_SEED = 9  # the fixed stream of the pacer's jitter (``fixed_jitter``)


@pytest.fixture(autouse=True)
def fixed_jitter(monkeypatch: pytest.MonkeyPatch) -> None:
    """The pacer's jitter from a fixed stream instead of one keyed by the run's fresh secrets. Keyed,
    the jitter of 11 to 14 gaps correlates with the steps by chance beyond |rho| 0.6 in a few runs
    of a hundred; fixed, the paced gaps (pad plus jitter) are the same on every run of the test,
    their correlation with the steps that of these draws (``test_the_fixed_jitter_is_uncorrelated_with_the_steps``)."""
    real = seeding.Streams.rng

    def rng(self: seeding.Streams, stream: int, index: int = 0) -> np.random.Generator:
        return np.random.default_rng([JITTER_SEED, index]) if stream == seeding.PACING else real(self, stream, index)

    monkeypatch.setattr(seeding.Streams, "rng", rng)


def test_the_fixed_jitter_is_uncorrelated_with_the_steps() -> None:
    """The draws the paced runs below get: request n waits for draw n (request 0 leaves at once);
    with four requests a round, the round's gap is that of its first request or its least wait."""
    draws = [float(np.random.default_rng([JITTER_SEED, n]).uniform()) for n in range(4 * len(ROUND_LONGEST))]
    assert abs(spearman(draws[1:len(SEARCH)], SEARCH[:-1])) < 0.3
    for per_round in ([draws[4 * r] for r in range(1, len(ROUND_LONGEST))], [min(draws[4 * r:4 * r + 4]) for r in range(1, len(ROUND_LONGEST))]):
        assert abs(spearman(per_round, ROUND_LONGEST[:-1])) < 0.3


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> VirtualClock:
    """The run's clock: virtual, so that every gap is the episode's steps x STEP_S (plus the pacer's wait)."""
    c = VirtualClock()
    c.install(monkeypatch, serial_requests=True)
    return c


def _run(tmp_path: Path, clock: VirtualClock, pace: bool) -> Path:
    run_dir = tmp_path / ("paced" if pace else "plain")
    lengths = WARMUP + SEARCH
    with offline_llm(), ppprops.create_study("CartPole", storage=run_dir, method="pp", warmup=len(WARMUP), iterations=len(SEARCH),
                                             seed=1, prompt={"form": "chat"}, evaluation={"final_episodes": 0, "select_top": 0},
                                             privacy={"pace_requests": pace}) as study:
        while not study.done:
            trial = study.ask()
            steps = lengths[trial.number]
            clock.sleep(STEP_S * steps)  # the rig runs the episode in (virtual) real time
            study.tell(trial, float(steps), diagnostics={"episode_length": steps, "termination": "pole_fell"})
    return run_dir


def _rho(report) -> float:  # type: ignore[no-untyped-def]
    (note,) = [n for n in report.notes if n.startswith("request timing")]
    return float(note.split("Spearman ")[1].split(" ")[0])


def test_gaps_that_follow_the_episodes_are_reported_and_pacing_removes_them(tmp_path: Path, clock: VirtualClock) -> None:
    plain = audit_run(_run(tmp_path, clock, pace=False), simulate=False)
    timing = [f for f in plain.findings if f.kind in ("request_timing", "request-timing")]
    assert len(timing) == 1 and "Spearman" in timing[0].detail and "episode steps" in timing[0].detail, plain.format()
    assert _rho(plain) == 1.0  # each gap is the steps told, x STEP_S
    # pp's verdict says what closes the channels it keeps: pp-hardened, and pacing for the clock when the clock is among them
    clock_exposed = timing[0].severity == "exposed"
    tail = ", with --pace-requests on for the request timing" if clock_exposed else ""
    assert plain.verdict().startswith("EXPOSED") and plain.verdict().endswith(f"(pp-hardened closes them{tail})."), plain.verdict()

    t0 = clock.time()
    paced_dir = _run(tmp_path, clock, pace=True)
    paced_s = clock.time() - t0
    paced = audit_run(paced_dir, simulate=False)
    assert not [f for f in paced.findings if f.kind in ("request_timing", "request-timing")], paced.format()
    assert abs(_rho(paced)) < 0.3 and any("(requests paced)" in n for n in paced.notes)
    with open_store(paced_dir) as store:
        state = store.pacing_state()
    assert state["requests"] == len(SEARCH) and state["longest_gap"] >= STEP_S * max(WARMUP)
    # every paced gap is at least the pad: twice the longest warm-up trial
    assert paced_s >= len(SEARCH) * 2 * STEP_S * max(WARMUP)
    # the privacy report names the clock's finding per run, and the paced runs apart
    runs = [analyse_run(d, simulate=False) for d in (tmp_path / "plain", paced_dir)]
    assert runs[0].timing in ("channel", "exposed") and not runs[0].paced
    assert runs[1].timing == "" and runs[1].paced
    text = format_report(runs)
    assert "| CartPole | pp, paced | 1 |" in text and "| 0/1 / 0/1 | 0/1 |" in text, text


def _run_wide(tmp_path: Path, clock: VirtualClock, pace: bool) -> Path:
    run_dir = tmp_path / ("wide-paced" if pace else "wide-plain")
    lengths = WIDE_WARMUP + [n for longest in ROUND_LONGEST for n in (10, longest, 12, 8)]
    with offline_llm(), ppprops.create_study("CartPole", storage=run_dir, method="pp", warmup=len(WIDE_WARMUP),
                                             iterations=4 * len(ROUND_LONGEST), seed=1, prompt={"form": "chat"},
                                             evaluation={"final_episodes": 0, "select_top": 0, "parallel": 4},
                                             privacy={"pace_requests": pace}) as study:
        told = [0]  # trials told so far

        def worker(name: str) -> None:
            while True:
                try:
                    trial = study.ask(worker=name)
                except StudyComplete:
                    return
                number = trial.number
                steps = lengths[number]
                with clock.turn:  # the rigs' episodes one after another, in trial order: their stamps in that order
                    clock.turn.wait_for(lambda n=number: told[0] == n, timeout=120)
                    clock.sleep(STEP_S * steps)
                    study.tell(trial, float(steps), diagnostics={"episode_length": steps, "termination": "pole_fell"})
                    told[0] += 1
                    clock.turn.notify_all()

        threads = [threading.Thread(target=worker, args=(f"rig-{i}",)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    return run_dir


def test_a_round_of_parallel_requests_shows_its_trials_and_pacing_removes_it(tmp_path: Path, clock: VirtualClock) -> None:
    plain_dir = _run_wide(tmp_path, clock, pace=False)
    with open_store(plain_dir) as store:
        assert len(store.llm_calls()) == 4 * len(ROUND_LONGEST)  # one request per LLM candidate, four per round
    plain = audit_run(plain_dir, simulate=False)
    timing = [f for f in plain.findings if f.kind in ("request_timing", "request-timing")]
    assert len(timing) == 1 and "episode steps" in timing[0].detail, plain.format()
    (note,) = [n for n in plain.notes if n.startswith("request timing")]
    assert f"over {len(ROUND_LONGEST) - 1} gaps" in note  # one gap between each round and the next
    assert _rho(plain) == 1.0  # each gap is its round's four episodes, its longest plus 30 steps

    paced = audit_run(_run_wide(tmp_path, clock, pace=True), simulate=False)
    assert not [f for f in paced.findings if f.kind in ("request_timing", "request-timing")], paced.format()
    assert abs(_rho(paced)) < 0.3 and any("(requests paced)" in n for n in paced.notes)


@pytest.mark.parametrize("pace", [True])
def test_pacing_is_a_switch_of_every_preset(pace: bool) -> None:
    from ppprops.methods import resolve

    assert resolve("pp", pace_requests=pace).pace_requests and not resolve("pp-hardened").pace_requests


def test_a_resumed_run_does_not_take_its_downtime_for_an_evaluation(tmp_path: Path, clock: VirtualClock) -> None:
    """A paced study whose process stopped an hour ago, driven on by ``optimize`` (what ``resume``
    runs): the hour is not a gap to pad every later request to (``Pacer.restart``)."""
    run_dir = tmp_path / "r"
    with offline_llm(), ppprops.create_study("CartPole", storage=run_dir, method="pp", warmup=3, iterations=4, seed=1,
                                             prompt={"form": "chat"}, evaluation={"final_episodes": 0, "select_top": 0},
                                             privacy={"pace_requests": True}) as study:
        for _ in range(5):  # the warm-up and two LLM trials, told by hand
            trial = study.ask()
            study.tell(trial, 20.0, diagnostics={"episode_length": 20, "termination": "pole_fell"})
    with open_store(run_dir) as store:  # the process stopped an hour ago
        state = store.pacing_state()
        store.set_pacing_state({**state, "last_answer": state["last_answer"] - 3600.0})
    with offline_llm(), ppprops.load_study(run_dir) as study:
        study.optimize()
        assert study.done
    with open_store(run_dir) as store:
        after = store.pacing_state()
    assert after["requests"] == 4 and after["longest_gap"] < 60.0, after  # 3600 s without the restart
