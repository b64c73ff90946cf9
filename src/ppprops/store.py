"""The run store: one SQLite database (WAL) per run directory, written as the run goes.

Every evaluated candidate is inserted in its own transaction, with a unique (index), so a run
killed at any moment holds each evaluated candidate once or not at all, and ``resume`` picks up
from there. The schema carries a version for future migrations.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import StoreError
from .evaluation import Feedback

SCHEMA_VERSION = 1
DB_NAME = "run.sqlite"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS candidates (
    idx INTEGER PRIMARY KEY,
    iteration INTEGER NOT NULL,
    source TEXT NOT NULL,
    params TEXT NOT NULL,
    params_enc TEXT NOT NULL,
    feedback TEXT NOT NULL,
    feedback_enc TEXT NOT NULL,
    clipped INTEGER NOT NULL,
    seeds TEXT NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS llm_calls (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    iteration INTEGER NOT NULL,
    attempt INTEGER NOT NULL,
    request TEXT NOT NULL,
    response TEXT,
    content TEXT,
    reasoning TEXT,
    prompt_chars INTEGER NOT NULL,
    prompt_tokens INTEGER,
    completion_tokens INTEGER,
    latency_s REAL NOT NULL,
    ok INTEGER NOT NULL,
    error TEXT,
    parse_error TEXT,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS final_eval (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    candidate_idx INTEGER NOT NULL,
    returns TEXT NOT NULL,
    seeds TEXT NOT NULL,
    created REAL NOT NULL
);
"""


@dataclass(frozen=True)
class Candidate:
    """One evaluated policy, raw and encoded. Client-side only."""

    index: int
    iteration: int  # warm-up sample number, or LLM iteration
    source: str  # warmup | llm | fallback
    params: np.ndarray  # raw theta (decoded, clipped)
    params_enc: np.ndarray
    feedback: Feedback  # raw
    feedback_enc: Feedback  # rewards scaled (diagnostics as they are)
    clipped: int
    seeds: tuple[int, ...]
    note: str = ""

    @property
    def ret(self) -> float:
        return self.feedback.ret


@dataclass(frozen=True)
class FinalEval:
    candidate_index: int
    returns: tuple[float, ...]
    seeds: tuple[int, ...]

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns)) if self.returns else float("nan")

    @property
    def std(self) -> float:
        return float(np.std(self.returns)) if self.returns else float("nan")


class RunStore:
    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        try:
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
            version = self._meta("schema_version")
        except sqlite3.DatabaseError as e:
            raise StoreError(f"run store {self.path} is not a readable SQLite database ({e})") from None
        if version is None:
            self._set_meta("schema_version", str(SCHEMA_VERSION))
        elif int(version) > SCHEMA_VERSION:
            raise StoreError(f"run store {self.path} has schema {version}; this ppprops reads up to {SCHEMA_VERSION}")

    # -- plumbing -------------------------------------------------------------------------
    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def _meta(self, key: str) -> str | None:
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def _set_meta(self, key: str, value: str) -> None:
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, value))

    def close(self) -> None:
        self._db.close()

    # -- run-level ------------------------------------------------------------------------
    def init_run(self, run_id: str, config: dict[str, Any], key_fingerprint: str) -> None:
        if self._meta("run_id") is not None:
            raise StoreError(f"{self.path} already holds run {self._meta('run_id')}")
        with self._tx() as db:
            for k, v in (("run_id", run_id), ("config", json.dumps(config)), ("key_fingerprint", key_fingerprint),
                         ("status", "running"), ("created", str(time.time()))):
                db.execute("INSERT INTO meta (key, value) VALUES (?, ?)", (k, v))

    def run_id(self) -> str:
        rid = self._meta("run_id")
        if rid is None:
            raise StoreError(f"{self.path} holds no run")
        return rid

    def config(self) -> dict[str, Any]:
        raw = self._meta("config")
        if raw is None:
            raise StoreError(f"{self.path} holds no run configuration")
        return dict(json.loads(raw))

    def key_fingerprint(self) -> str:
        return self._meta("key_fingerprint") or ""

    def status(self) -> str:
        return self._meta("status") or "unknown"

    def set_status(self, status: str) -> None:
        self._set_meta("status", status)

    # -- candidates -----------------------------------------------------------------------
    def add_candidate(self, c: Candidate) -> None:
        try:
            with self._tx() as db:
                db.execute(
                    "INSERT INTO candidates (idx, iteration, source, params, params_enc, feedback, feedback_enc, clipped, seeds, note, created)"
                    " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        c.index, c.iteration, c.source,
                        json.dumps([float(v) for v in c.params]), json.dumps([float(v) for v in c.params_enc]),
                        json.dumps(c.feedback.to_json()), json.dumps(c.feedback_enc.to_json()),
                        c.clipped, json.dumps(list(c.seeds)), c.note, time.time(),
                    ),
                )
        except sqlite3.IntegrityError:
            raise StoreError(f"candidate {c.index} is already recorded in {self.path}") from None

    def candidates(self) -> list[Candidate]:
        rows = self._db.execute(
            "SELECT idx, iteration, source, params, params_enc, feedback, feedback_enc, clipped, seeds, note"
            " FROM candidates ORDER BY idx"
        ).fetchall()
        return [
            Candidate(
                index=r[0], iteration=r[1], source=r[2],
                params=np.asarray(json.loads(r[3])), params_enc=np.asarray(json.loads(r[4])),
                feedback=Feedback.from_json(json.loads(r[5])), feedback_enc=Feedback.from_json(json.loads(r[6])),
                clipped=r[7], seeds=tuple(json.loads(r[8])), note=r[9],
            )
            for r in rows
        ]

    # -- LLM exchanges --------------------------------------------------------------------
    def add_llm_call(self, iteration: int, attempt: int, ex: Any, parse_error: str | None) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT INTO llm_calls (iteration, attempt, request, response, content, reasoning, prompt_chars,"
                " prompt_tokens, completion_tokens, latency_s, ok, error, parse_error, created)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    iteration, attempt, ex.request, ex.response, ex.content, ex.reasoning, ex.prompt_chars,
                    ex.prompt_tokens, ex.completion_tokens, ex.latency_s, int(ex.ok), ex.error, parse_error, time.time(),
                ),
            )

    def llm_calls(self) -> list[dict[str, Any]]:
        cur = self._db.execute(
            "SELECT id, iteration, attempt, request, response, content, reasoning, prompt_chars, prompt_tokens,"
            " completion_tokens, latency_s, ok, error, parse_error FROM llm_calls ORDER BY id"
        )
        cols = [d[0] for d in cur.description]
        out = []
        for row in cur.fetchall():
            d = dict(zip(cols, row))
            d["ok"] = bool(d["ok"])
            out.append(d)
        return out

    # -- final evaluation -----------------------------------------------------------------
    def set_final_eval(self, fe: FinalEval) -> None:
        with self._tx() as db:
            db.execute(
                "INSERT OR REPLACE INTO final_eval (id, candidate_idx, returns, seeds, created) VALUES (1, ?, ?, ?, ?)",
                (fe.candidate_index, json.dumps(list(fe.returns)), json.dumps(list(fe.seeds)), time.time()),
            )

    def final_eval(self) -> FinalEval | None:
        row = self._db.execute("SELECT candidate_idx, returns, seeds FROM final_eval WHERE id = 1").fetchone()
        if row is None:
            return None
        return FinalEval(candidate_index=row[0], returns=tuple(json.loads(row[1])), seeds=tuple(json.loads(row[2])))


def open_store(run_dir: Path, *, create: bool = False) -> RunStore:
    path = Path(run_dir) / DB_NAME
    if not create and not path.exists():
        raise StoreError(f"{run_dir} is not a ppprops run directory (no {DB_NAME})")
    return RunStore(path)
