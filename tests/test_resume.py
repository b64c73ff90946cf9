"""An interrupted run continues with `ppprops resume`, with the same secrets, re-evaluating nothing."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.errors import LLMError
from ppprops.llm.client import EndpointClient
from ppprops.runner import resume, start
from ppprops.store import open_store

from support import make_config

pytestmark = pytest.mark.llm


def _count(db: Path) -> int:
    try:
        with sqlite3.connect(db, timeout=5) as con:
            return int(con.execute("SELECT COUNT(*) FROM candidates").fetchone()[0])
    except sqlite3.Error:
        return 0


@pytest.mark.parametrize("kill_after", [2, 5])
def test_resume_after_kill_9(tmp_path: Path, capsys, kill_after: int) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "ppprops", "run", "--env", "CartPole", "--method", "pp", "--warmup", "3",
           "--iterations", "4", "--final-episodes", "3", "--select-top", "0", "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    while _count(out / "run.sqlite") < kill_after and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    store = open_store(out)
    before = store.candidates()
    store.close()
    assert kill_after <= len(before) < 7, "the run was not interrupted midway"
    key_before = (out / "secrets.key").read_bytes()

    assert main(["resume", str(out), "--quiet"]) == 0
    capsys.readouterr()
    store = open_store(out)
    after = store.candidates()
    assert store.status() == "finished" and store.final_eval() is not None
    store.close()
    assert [c.index for c in after] == list(range(7))  # every candidate exactly once
    for b, a in zip(before, after):  # nothing recorded was re-evaluated or changed
        np.testing.assert_array_equal(a.params, b.params)
        assert a.feedback == b.feedback and a.source == b.source
    assert (out / "secrets.key").read_bytes() == key_before
    assert (out / "best_policy.json").exists()


def test_endpoint_failure_stops_cleanly_and_resumes(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    real = EndpointClient.send
    calls = {"n": 0}

    def flaky(self, request, *, seed=None):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 3:
            raise LLMError("injected: endpoint gone")
        return real(self, request, seed=seed)

    monkeypatch.setattr(EndpointClient, "send", flaky)
    out = tmp_path / "run"
    with pytest.raises(LLMError):
        start(make_config(warmup=3, iterations=4, parse_retries=0), out)
    store = open_store(out)
    partial = store.candidates()
    assert store.status() == "failed: injected: endpoint gone" and len(partial) == 5  # 3 warm-up + 2 LLM candidates; resumable
    store.close()

    resume(out)
    store = open_store(out)
    done = store.candidates()
    assert [c.index for c in done] == list(range(7)) and store.status() == "finished"
    assert [c.iteration for c in done[3:]] == [0, 1, 2, 3]
    store.close()


def test_resume_of_a_finished_run_evaluates_nothing(tmp_path: Path) -> None:
    out = tmp_path / "run"
    start(make_config(warmup=2, iterations=0, final_episodes=2), out)
    store = open_store(out)
    n, fe = len(store.candidates()), store.final_eval()
    store.close()
    resume(out)
    store = open_store(out)
    assert len(store.candidates()) == n and store.final_eval() == fe
    store.close()
    doc = json.loads((out / "best_policy.json").read_text())
    assert doc["final_eval"]["episodes"] == 2
