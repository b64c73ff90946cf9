"""The provider's clock: on a rig stepped in real time, the gap between an answer and the next
request follows the episode the client just ran. The audit measures it on the run's recorded
request times (``privacy.timing``) and reports it; with ``pace_requests`` (``llm.pacing``) the gaps
no longer follow the episodes and the audit finds nothing. Driven through ask/tell with the
offline stand-in optimizer, each trial's evaluation a sleep of 2 ms per step."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import ppprops
from ppprops.privacy.audit import audit_run
from ppprops.store import open_store

from support import offline_llm

STEP_S = 0.002
WARMUP = [40, 200, 90]  # the warm-up's episode lengths: random policies span the range
SEARCH = [int(x) for x in np.random.default_rng(0).permutation(np.linspace(10, 190, 14)).round()]


def _run(tmp_path: Path, pace: bool) -> Path:
    run_dir = tmp_path / ("paced" if pace else "plain")
    lengths = WARMUP + SEARCH
    with offline_llm(), ppprops.create_study("CartPole", storage=run_dir, method="pp", warmup=len(WARMUP), iterations=len(SEARCH),
                                             seed=1, prompt={"form": "chat"}, evaluation={"final_episodes": 0, "select_top": 0},
                                             privacy={"pace_requests": pace}) as study:
        while not study.done:
            trial = study.ask()
            steps = lengths[trial.number]
            time.sleep(STEP_S * steps)  # the rig runs the episode in real time
            study.tell(trial, float(steps), diagnostics={"episode_length": steps, "termination": "pole_fell"})
    return run_dir


def _rho(report) -> float:  # type: ignore[no-untyped-def]
    (note,) = [n for n in report.notes if n.startswith("request timing")]
    return float(note.split("Spearman ")[1].split(" ")[0])


def test_gaps_that_follow_the_episodes_are_reported_and_pacing_removes_them(tmp_path: Path) -> None:
    plain = audit_run(_run(tmp_path, pace=False), simulate=False)
    timing = [f for f in plain.findings if f.kind in ("request_timing", "request-timing")]
    assert len(timing) == 1 and "Spearman" in timing[0].detail and "episode steps" in timing[0].detail, plain.format()
    assert _rho(plain) > 0.9  # the gaps follow the steps told

    t0 = time.monotonic()
    paced_dir = _run(tmp_path, pace=True)
    paced_s = time.monotonic() - t0
    paced = audit_run(paced_dir, simulate=False)
    assert not [f for f in paced.findings if f.kind in ("request_timing", "request-timing")], paced.format()
    assert abs(_rho(paced)) < 0.6 and any("(requests paced)" in n for n in paced.notes)
    with open_store(paced_dir) as store:
        state = store.pacing_state()
    assert state["requests"] == len(SEARCH) and state["longest_gap"] >= STEP_S * max(WARMUP)
    # every paced gap is at least the pad: twice the longest warm-up trial
    assert paced_s >= len(SEARCH) * 2 * STEP_S * max(WARMUP) * 0.9


@pytest.mark.parametrize("pace", [True])
def test_pacing_is_a_switch_of_every_preset(pace: bool) -> None:
    from ppprops.methods import resolve

    assert resolve("pp", pace_requests=pace).pace_requests and not resolve("pp-hardened").pace_requests
