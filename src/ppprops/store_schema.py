"""The run store's file format: its tables, the migrations of older stores, and its journal mode.

``ppprops.store.RunStore`` opens a store through ``enable_wal`` and ``create_or_migrate``; nothing
here keeps a connection or knows the rows' meaning beyond their columns.

Schema versions: 1 (initial); 2 adds ``llm_calls.error_kind``, ``retry`` and ``answer_source``
(transport faults and answers taken from the reasoning text); 3 adds ``candidates.ask_s`` and
``eval_s`` (where an iteration's time goes); 4 adds the ``pending`` table (the trial a study has
asked for and not yet been told: stored before ``ask`` returns, so a restart asks nothing twice)
and ``llm_calls.form`` and ``decisions`` (the prompt form of each call and the public choices it
made, which the audit reads); 5 names the form of every call (calls recorded before forms were
named get the form their body shows, ``wire.forms.recorded_form``, once); 6 adds
``llm_calls.answered``: every try is written before its bytes leave (``begin_llm_call``, answered
0) and completed with its answer after (``complete_llm_call``, answered 1), so a process killed
while a request is in flight leaves that request in the store, marked unanswered (calls recorded
before were recorded after their answer: answered 1), and ``llm_calls.sent``, when each try left
(Unix seconds; unknown, NULL, for calls recorded before: their ``created`` is when the answer
came); 7 lets several trials be pending at once (``--parallel P``), each held by a worker
(``pending.worker``), and keeps the trials that failed with their reason (the ``failed``
table), out of the candidates. Older stores are migrated in place.
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

from .errors import StoreError

SCHEMA_VERSION = 7

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
    created REAL NOT NULL,
    error_kind TEXT,
    retry INTEGER NOT NULL DEFAULT 0,
    answer_source TEXT
);
CREATE TABLE IF NOT EXISTS pending (
    idx INTEGER PRIMARY KEY,
    phase TEXT NOT NULL,
    iteration INTEGER NOT NULL,
    source TEXT NOT NULL,
    params TEXT NOT NULL,
    seeds TEXT NOT NULL,
    clipped INTEGER NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    ask_s REAL,
    n_s INTEGER NOT NULL,
    n_a INTEGER NOT NULL,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS failed (
    idx INTEGER PRIMARY KEY,
    phase TEXT NOT NULL,
    iteration INTEGER NOT NULL,
    source TEXT NOT NULL,
    params TEXT NOT NULL,
    seeds TEXT NOT NULL,
    clipped INTEGER NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    ask_s REAL,
    n_s INTEGER NOT NULL,
    n_a INTEGER NOT NULL,
    reevaluates INTEGER,
    worker TEXT,
    reason TEXT NOT NULL,
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

# Columns added after schema 1, with their definitions, in the order they were added.
_ADDED_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("llm_calls", "error_kind", "TEXT"),
    ("llm_calls", "retry", "INTEGER NOT NULL DEFAULT 0"),
    ("llm_calls", "answer_source", "TEXT"),
    ("candidates", "ask_s", "REAL"),
    ("candidates", "eval_s", "REAL"),
    ("llm_calls", "form", "TEXT"),
    ("llm_calls", "decisions", "TEXT"),
    ("candidates", "reevaluates", "INTEGER"),
    ("pending", "reevaluates", "INTEGER"),
    ("llm_calls", "answered", "INTEGER NOT NULL DEFAULT 1"),
    ("llm_calls", "sent", "REAL"),
    ("pending", "worker", "TEXT"),
)


def enable_wal(db: sqlite3.Connection, timeout_s: float) -> None:
    """Switch the store ``db`` to WAL mode, waiting up to ``timeout_s`` while another process holds
    the lock: SQLite may answer this pragma "database is locked" at once, without its busy handler,
    while another connection creates the file or recovers its WAL index.

    Raises:
        sqlite3.OperationalError: any other failure, or the lock still held after ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    delay = 0.005
    while True:
        try:
            db.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as e:
            if not ("locked" in str(e) or "busy" in str(e)) or time.monotonic() >= deadline:
                raise
        time.sleep(delay)
        delay = min(delay * 2, 0.2)


def create_or_migrate(db: sqlite3.Connection, path: Path) -> None:
    """Create the tables a new store lacks, or bring an older store up to ``SCHEMA_VERSION`` in
    place (inside the caller's write transaction, so one writer does it while the others wait).

    Args:
        db: the store's connection, in a write transaction.
        path: the store's file, for the error's message.

    Raises:
        StoreError: the store has a newer schema than this ppprops reads.
    """
    for stmt in _SCHEMA.split(";"):
        if stmt.strip():
            db.execute(stmt)
    row = db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    version = None if row is None else int(row[0])
    if version is not None and version > SCHEMA_VERSION:
        raise StoreError(f"run store {path} has schema {version}; this ppprops reads up to {SCHEMA_VERSION}")
    for table, column, decl in _ADDED_COLUMNS:  # from 1: add what is missing (new stores have it all)
        have = {r[1] for r in db.execute(f"PRAGMA table_info({table})")}
        if column not in have:
            db.execute(f"ALTER TABLE {table} ADD COLUMN {column} {decl}")
    if version is not None and version < 5:  # every call names its form from schema 5 on
        from .wire.forms import recorded_form

        for call_id, request in db.execute("SELECT id, request FROM llm_calls WHERE form IS NULL").fetchall():
            db.execute("UPDATE llm_calls SET form = ? WHERE id = ?", (recorded_form(str(request)), call_id))
    if version != SCHEMA_VERSION:
        db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
