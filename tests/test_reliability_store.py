"""The store under stress: several processes writing one database lose nothing, a schema-1 store
migrates in place, and a full disk is a one-line StoreError that leaves the store intact."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import numpy as np
import pytest

from ppprops.errors import StoreError
from ppprops.evaluation import Feedback
from ppprops.store import SCHEMA_VERSION, Candidate, RunStore

WRITERS, ROWS = 4, 300

_WRITER = textwrap.dedent(
    """
    import os, sys, time, types
    import numpy as np
    from ppprops.evaluation import Feedback
    from ppprops.store import Candidate, RunStore

    path, w, rows, go = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    store = RunStore(path)
    open(go + f".ready{w}", "w").close()
    while not os.path.exists(go):  # start together: imports take longer than the writing
        time.sleep(0.005)
    fb = Feedback(ret=float(w), components={"c": 1.0}, diagnostics={"episode_length": 3.0}, episode_returns=(float(w),))
    for i in range(rows):
        if i == rows // 2:  # meet half way, so that the writers overlap however the OS schedules them
            open(go + f".half{w}", "w").close()
            deadline = time.monotonic() + 120
            while sum(os.path.exists(go + f".half{k}") for k in range(int(sys.argv[5]))) < int(sys.argv[5]) and time.monotonic() < deadline:
                time.sleep(0.005)
        idx = w * 100000 + i  # each writer its own index range, as runs sharing an experiment store would
        theta = np.full(4, float(i))
        store.add_candidate(Candidate(idx, i, "warmup", theta, theta, fb, fb, 0, (i,)))
        ex = types.SimpleNamespace(request=f"w{w}-{i}", response=None, content="{}", reasoning=None, prompt_chars=2,
                                   prompt_tokens=None, completion_tokens=None, latency_s=0.0, ok=True, error=None)
        store.add_llm_call(i, 0, ex, None, form="chat")
    store.close()
    """
)


_OPENER = textwrap.dedent(
    """
    import os, sys, time
    from ppprops.store import RunStore

    path, go, w = sys.argv[1], sys.argv[2], sys.argv[3]
    open(go + ".ready" + w, "w").close()
    while not os.path.exists(go):
        time.sleep(0.001)
    RunStore(path).close()
    """
)


def test_processes_opening_a_new_store_at_once_all_get_it(tmp_path: Path) -> None:
    """Eight processes open the same new store at the same moment, ten times over. Every open
    succeeds: SQLite may refuse the switch to WAL with "database is locked" at once, without waiting
    on its busy timeout, while another process is creating the file (this failed about one open in
    twenty before the store retried it)."""
    failures = []
    for round_ in range(10):
        d = tmp_path / str(round_)
        d.mkdir()
        go = d / "go"
        procs = [subprocess.Popen([sys.executable, "-c", _OPENER, str(d / "s.sqlite"), str(go), str(w)], stderr=subprocess.PIPE,
                                  text=True) for w in range(8)]  # fmt: skip
        deadline = time.monotonic() + 120
        while len(list(d.glob("go.ready*"))) < 8 and time.monotonic() < deadline and all(p.poll() is None for p in procs):
            time.sleep(0.005)
        go.touch()
        errors = [p.communicate(timeout=240)[1] for p in procs]
        failures += [(err.strip().splitlines() or [f"exit {p.returncode}"])[-1] for p, err in zip(procs, errors) if p.returncode]
    assert failures == []
    with RunStore(tmp_path / "0" / "s.sqlite") as store:
        assert store.integrity_check() == "ok"


def test_several_processes_writing_one_store_lose_nothing(tmp_path: Path) -> None:
    db, go = tmp_path / "shared.sqlite", tmp_path / "go"
    procs = [
        subprocess.Popen([sys.executable, "-c", _WRITER, str(db), str(w), str(ROWS), str(go), str(WRITERS)], stderr=subprocess.PIPE, text=True)
        for w in range(WRITERS)
    ]
    deadline = time.monotonic() + 120
    while len(list(tmp_path.glob("go.ready*"))) < WRITERS and time.monotonic() < deadline and all(p.poll() is None for p in procs):
        time.sleep(0.01)
    go.touch()
    errors = [p.communicate(timeout=240)[1] for p in procs]
    assert all(p.returncode == 0 for p in procs), errors
    store = RunStore(db)
    cands, calls = store.candidates(), store.llm_calls()
    assert store.integrity_check() == "ok"
    store.close()
    assert len(cands) == WRITERS * ROWS and len({c.index for c in cands}) == WRITERS * ROWS
    assert sorted(c["request"] for c in calls) == sorted(f"w{w}-{i}" for w in range(WRITERS) for i in range(ROWS))
    for c in cands:  # every row whole: its writer's return and its own parameters
        assert c.ret == c.index // 100000 and np.all(c.params == c.iteration)
    with sqlite3.connect(db) as con:  # the writers really ran at the same time (their commits interleave)
        order = [r[0] // 100000 for r in con.execute("SELECT idx FROM candidates ORDER BY created, rowid")]
    switches = sum(a != b for a, b in zip(order, order[1:], strict=False))
    assert switches > WRITERS, f"writers did not overlap ({switches} switches)"


_SCHEMA_1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE candidates (idx INTEGER PRIMARY KEY, iteration INTEGER NOT NULL, source TEXT NOT NULL, params TEXT NOT NULL,
    params_enc TEXT NOT NULL, feedback TEXT NOT NULL, feedback_enc TEXT NOT NULL, clipped INTEGER NOT NULL,
    seeds TEXT NOT NULL, note TEXT NOT NULL DEFAULT '', created REAL NOT NULL);
CREATE TABLE llm_calls (id INTEGER PRIMARY KEY AUTOINCREMENT, iteration INTEGER NOT NULL, attempt INTEGER NOT NULL,
    request TEXT NOT NULL, response TEXT, content TEXT, reasoning TEXT, prompt_chars INTEGER NOT NULL,
    prompt_tokens INTEGER, completion_tokens INTEGER, latency_s REAL NOT NULL, ok INTEGER NOT NULL, error TEXT,
    parse_error TEXT, created REAL NOT NULL);
CREATE TABLE final_eval (id INTEGER PRIMARY KEY CHECK (id = 1), candidate_idx INTEGER NOT NULL, returns TEXT NOT NULL,
    seeds TEXT NOT NULL, created REAL NOT NULL);
INSERT INTO meta VALUES ('schema_version', '1'), ('run_id', 'old-run');
INSERT INTO llm_calls (iteration, attempt, request, content, prompt_chars, latency_s, ok, parse_error, created)
    VALUES (0, 0, '{}', 'hello', 2, 0.5, 1, 'no_numbers', 0),
           (1, 0, '{"model": "m", "prompt": "return: 1\\nparams: ["}', '0:1]', 2, 0.5, 1, NULL, 0);
INSERT INTO candidates VALUES (0, 0, 'warmup', '[1.0]', '[2.0]', '{"return": 3.0, "components": {}, "diagnostics": {}}',
    '{"return": 6.0, "components": {}, "diagnostics": {}}', 0, '[7]', '', 0);
"""


def test_a_schema_1_store_migrates_in_place(tmp_path: Path) -> None:
    db = tmp_path / "old.sqlite"
    with sqlite3.connect(db) as con:
        con.executescript(_SCHEMA_1)
    store = RunStore(db)
    assert store.schema_version() == SCHEMA_VERSION == 7 and store.run_id() == "old-run"
    assert store.pending_trials() == [] and store.failed_trials() == [] and store.next_number() == 1  # schema 7: workers, failed trials
    (first,) = store.candidates()  # an old row reads back, its timings unknown
    assert first.ret == 3.0 and first.ask_s is None and first.eval_s is None
    fb = Feedback(ret=4.0)
    store.add_candidate(Candidate(index=1, iteration=0, source="llm", params=np.ones(1), params_enc=np.ones(1), feedback=fb,
                                  feedback_enc=fb, clipped=0, seeds=(8,), ask_s=1.5, eval_s=0.25))
    assert [(i, src, a, e) for i, src, _, _, a, e in store.candidate_times()] == [(0, "warmup", None, None), (1, "llm", 1.5, 0.25)]
    old, document = store.llm_calls()
    assert old["parse_error"] == "no_numbers" and old["retry"] == 0 and old["error_kind"] is None
    assert (old["form"], document["form"]) == ("chat", "document")  # every call names its form, old ones as their body shows
    assert old["answered"] and document["answered"]  # recorded after their answers: none was left in flight
    ex = types.SimpleNamespace(request="{}", response=None, content=None, reasoning=None, prompt_chars=2, prompt_tokens=None,
                               completion_tokens=None, latency_s=0.1, ok=False, error="timeout", error_kind="timeout", retry=1)
    store.add_llm_call(1, 0, ex, None, form="chat")
    assert store.llm_calls()[-1]["error_kind"] == "timeout" and store.llm_calls()[-1]["retry"] == 1
    store.close()
    RunStore(db).close()  # opening again is a no-op

    with sqlite3.connect(db) as con:
        con.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    with pytest.raises(StoreError, match="has schema 99"):
        RunStore(db)


def test_a_full_disk_is_one_store_error_and_the_store_stays_intact(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "s.sqlite")
    pages = store._db.execute("PRAGMA page_count").fetchone()[0]
    store._db.execute(f"PRAGMA max_page_count = {pages + 2}")  # SQLite's own limit: real SQLITE_FULL errors
    fb = Feedback(ret=1.0, components={}, diagnostics={}, episode_returns=(1.0,))
    written = 0
    with pytest.raises(StoreError) as info:
        for i in range(10_000):
            theta = np.full(200, 1.0 / 3.0)
            store.add_candidate(Candidate(i, i, "warmup", theta, theta, fb, fb, 0, (i,)))
            written += 1
    msg = str(info.value)
    assert "disk is full" in msg and "ppprops resume" in msg and "\n" not in msg
    assert store.integrity_check() == "ok"
    assert [c.index for c in store.candidates()] == list(range(written)) and written > 0
    store.close()
