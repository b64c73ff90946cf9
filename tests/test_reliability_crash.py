"""Crash safety: `kill -9` at many moments (starting, warm-up, LLM calls, final evaluation,
policy-file writing), then `ppprops resume` finishes with every candidate recorded exactly once,
the same key file, nothing recorded changed, and a store that passes SQLite's integrity check."""

from __future__ import annotations

import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ppprops.cli import main
from ppprops.store import open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer

WARMUP, ITERATIONS = 60, 10  # a long warm-up, so a kill can land inside it
TOTAL = WARMUP + ITERATIONS
KILLS = 16


def _query(db: Path, sql: str) -> list[tuple[object, ...]]:
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5) as con:
            return con.execute(sql).fetchall()
    except sqlite3.Error:
        return []


def _count(db: Path) -> int:
    rows = _query(db, "SELECT COUNT(*) FROM candidates")
    return int(rows[0][0]) if rows else 0  # type: ignore[call-overload]


def _phase(out: Path) -> str:
    db = out / "run.sqlite"
    if not db.exists():
        return "starting"
    n = _count(db)
    if n < WARMUP:
        return "warmup"
    if n < TOTAL:
        return "llm"
    if not (out / "best_policy.json").exists():
        return "final_eval"
    return "policy_written"


Snapshot = dict[int, tuple[list[float], dict[str, object], str]]


def _check_after_kill(out: Path, snapshot: Snapshot, key: bytes | None) -> bytes | None:
    """The invariants that must hold after any kill; returns the key file's bytes."""
    if not out.exists():  # killed while starting: nothing at --out, never half a run directory
        return None
    db = out / "run.sqlite"
    assert db.exists() and (out / "secrets.key").exists(), "a run directory appeared incomplete"
    con = sqlite3.connect(db, timeout=10)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        rows = con.execute("SELECT idx, params, feedback, source FROM candidates ORDER BY idx").fetchall()
    finally:
        con.close()
    assert [r[0] for r in rows] == list(range(len(rows)))  # each once, no gap
    for idx, params, feedback, source in rows:
        entry = (json.loads(params), json.loads(feedback), source)
        assert snapshot.setdefault(idx, entry) == entry  # a recorded candidate never changes
    now = (out / "secrets.key").read_bytes()
    assert key is None or now == key  # the same secrets throughout
    if (out / "best_policy.json").exists():
        json.loads((out / "best_policy.json").read_text())  # never half a file
    return now


def test_kill_9_at_many_moments_then_resume(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    rng = random.Random(7)
    fault = FaultConfig(fault_rate=0.5, kinds=("delay", "http_503", "reset", "empty"), delay_max_s=0.15, seed=3)
    runs: list[Path] = []
    phases: list[str] = []
    with FaultServer(fault) as server:
        base = [sys.executable, "-m", "ppprops"]
        llm = ["--base-url", server.base_url, "--model", "fault", "--structured", "json_schema", "--timeout", "2",
               "--retry-base-delay", "0.01", "--retry-max-delay", "0.05", "--on-llm-failure", "skip"]
        out, snapshot, key = tmp_path / "r0", {}, None  # type: ignore[var-annotated]
        runs.append(out)
        triggers: list[Callable[[Path], bool]] = []
        for i in range(KILLS):
            if i and i % 4 == 0 and out.exists():  # every four kills, a fresh run, so each phase gets its turn
                out, snapshot, key = tmp_path / f"r{len(runs)}", {}, None
                runs.append(out)
            if not (out / "run.sqlite").exists():
                cmd = [*base, "run", "--env", "CartPole", "--warmup", str(WARMUP), "--iterations", str(ITERATIONS),
                       "--final-episodes", "20", "--select-top", "0", "--episodes", "3", "--out", str(out), "--quiet", *llm]
            else:
                cmd = [*base, "resume", str(out), "--quiet"]
            kind = (1, 2, 0, 3)[i % 4]  # in the order a run goes through its phases
            if kind == 0:  # a random moment, from process start-up on
                deadline = time.monotonic() + rng.uniform(0.0, 2.5)
                trigger: Callable[[Path], bool] = lambda o, d=deadline: time.monotonic() >= d  # noqa: E731
            elif kind == 1:  # mid warm-up or just after it
                target = rng.randint(1, WARMUP // 3)
                trigger = lambda o, t=target: _count(o / "run.sqlite") >= t  # noqa: E731
            elif kind == 2:  # among the LLM iterations
                target = rng.randint(WARMUP + 1, TOTAL - 1)
                trigger = lambda o, t=target: _count(o / "run.sqlite") >= t  # noqa: E731
            else:  # the final evaluation or writing the policy file
                target = TOTAL
                trigger = lambda o, t=target: _count(o / "run.sqlite") >= t  # noqa: E731
            triggers.append(trigger)
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            limit = time.monotonic() + 60
            while proc.poll() is None and not trigger(out) and time.monotonic() < limit:
                time.sleep(0.005)
            if kind == 3:
                time.sleep(rng.uniform(0.0, 0.4))  # somewhere in the final evaluation / policy write
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
                phases.append(_phase(out))
                key = _check_after_kill(out, snapshot, key)
            else:  # it finished first: check it, then carry on with a fresh run
                assert proc.returncode == 0
                _check_after_kill(out, snapshot, key)
                out, snapshot, key = tmp_path / f"r{len(runs)}", {}, None
                runs.append(out)
        # Where each kill landed depends on the machine's speed (a run may finish before its kill),
        # so only "some kill landed" is asserted; each landed kill was checked by _check_after_kill.
        assert phases, "no kill landed before its run finished"

        for out in runs:  # resume every run to its end
            if not out.exists():
                continue
            key_before = (out / "secrets.key").read_bytes()
            store = open_store(out)
            before = store.candidates()
            store.close()
            assert main(["resume", str(out), "--quiet"]) == 0
            capsys.readouterr()
            store = open_store(out)
            after = store.candidates()
            assert store.status() == "finished" and store.final_eval() is not None
            assert store.integrity_check() == "ok"
            store.close()
            assert [c.index for c in after] == list(range(TOTAL))
            for b, a in zip(before, after[: len(before)], strict=True):
                np.testing.assert_array_equal(a.params, b.params)
                assert a.feedback == b.feedback and a.source == b.source
            assert (out / "secrets.key").read_bytes() == key_before
            assert json.loads((out / "best_policy.json").read_text())["search"]["candidate"] in range(TOTAL)
            assert not list(out.glob(".best_policy.json.*"))  # no stale temporary file left behind
