"""The run store: one SQLite database (WAL) per run directory, written as the run goes.

Every evaluated candidate is inserted in its own transaction, with a unique (index), so a run
killed at any moment holds each evaluated candidate once or not at all, and ``resume`` picks up
from there. Several processes may write one store at once: WAL, a busy timeout and
``BEGIN IMMEDIATE`` serialise the writers without losing a row. Every SQLite failure (a full disk,
an I/O error, a lock held too long) surfaces as a one-line ``StoreError``.

The tables, their schema versions and the migration of older stores: ``ppprops.store_schema``.
Changes the LLM client made to its requests (a parameter the endpoint refused, a larger token
budget) are kept in the ``meta`` key ``llm_adaptations`` (a JSON list), and where each LLM client
session began (a run's start, each resume) in ``llm_sessions``, so no schema change was needed for
them.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import StoreError
from .status import RunStatus
from .store_schema import SCHEMA_VERSION as SCHEMA_VERSION  # re-exported: the schema this ppprops writes
from .store_schema import create_or_migrate, enable_wal
from .values import Candidate, Feedback, FinalEval, Trial

BUSY_TIMEOUT_S = 60.0
DB_NAME = "run.sqlite"  # the store's file in a run directory (the directory's other files: ppprops.rundir)

# What a try written ahead holds until its answer completes it: to every reader it is a failed
# try of this kind, so a process that died with it in flight leaves a try the audit reads and
# ``show`` counts.
UNANSWERED = "unanswered"
UNANSWERED_ERROR = ("unanswered: the request was sent and no answer was recorded (still in flight, or the process "
                    "ended while it was)")


def _describe(e: sqlite3.Error, path: Path) -> str:
    """One line for a SQLite failure, naming the cause a user can act on."""
    text = str(e)
    low = text.lower()
    if "disk is full" in low or getattr(e, "sqlite_errorname", "") == "SQLITE_FULL":
        return f"run store {path}: the disk is full ({text}); free space, then continue with 'ppprops resume'"
    if "locked" in low or "busy" in low:
        return f"run store {path} stayed locked by another process for {BUSY_TIMEOUT_S:g} s ({text})"
    if "readonly" in low or "read-only" in low:
        return f"run store {path} is read-only ({text})"
    if "malformed" in low or "not a database" in low:
        return f"run store {path} is not a readable SQLite database ({text})"
    return f"run store {path}: {e.__class__.__name__}: {text}"


class _Rows:
    """A query's rows, read whole (``fetchone``/``fetchall``/``description`` as a cursor's)."""

    def __init__(self, rows: list[Any], description: Any) -> None:
        self.rows, self.description = rows, description

    def fetchone(self) -> Any:
        return self.rows[0] if self.rows else None

    def fetchall(self) -> list[Any]:
        return self.rows


# -- rows -------------------------------------------------------------------------------------
# How values become rows and rows values, inside a transaction the caller holds. The stamps read
# this module's ``time`` (the tests' virtual clock replaces it).

_TRIAL_COLUMNS = "idx, phase, iteration, source, params, seeds, clipped, note, ask_s, n_s, n_a, reevaluates, worker"

_CANDIDATE_COLUMNS = ("idx, iteration, source, params, params_enc, feedback, feedback_enc, clipped, seeds, note, ask_s, eval_s,"
                      " reevaluates")

_LLM_CALL_COLUMNS = ("id, iteration, attempt, request, response, content, reasoning, prompt_chars, prompt_tokens,"
                     " completion_tokens, latency_s, ok, error, parse_error, error_kind, retry, answer_source, form, decisions,"
                     " answered, created, sent")


def _trial(row: Any) -> Trial:
    """The trial of a ``pending`` or ``failed`` row read as ``_TRIAL_COLUMNS``."""
    return Trial(number=row[0], phase=row[1], iteration=row[2], source=row[3], theta=np.asarray(json.loads(row[4])),
                 seeds=tuple(json.loads(row[5])), clipped=row[6], note=row[7], ask_s=row[8], n_s=row[9], n_a=row[10],
                 reevaluates=row[11], worker=row[12])


def _insert_pending(db: sqlite3.Connection, t: Trial) -> None:
    """Insert the trial ``t`` into ``pending``, stamped now."""
    db.execute(
        "INSERT INTO pending (idx, phase, iteration, source, params, seeds, clipped, note, ask_s, n_s, n_a, created,"
        " reevaluates, worker) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (t.number, t.phase, t.iteration, t.source, json.dumps([float(v) for v in t.theta]), json.dumps(list(t.seeds)),
         t.clipped, t.note, t.ask_s, t.n_s, t.n_a, time.time(), t.reevaluates, t.worker),
    )


def _candidate(row: Any) -> Candidate:
    """The candidate of a ``candidates`` row read as ``_CANDIDATE_COLUMNS``."""
    return Candidate(
        index=row[0], iteration=row[1], source=row[2],
        params=np.asarray(json.loads(row[3])), params_enc=np.asarray(json.loads(row[4])),
        feedback=Feedback.from_json(json.loads(row[5])), feedback_enc=Feedback.from_json(json.loads(row[6])),
        clipped=row[7], seeds=tuple(json.loads(row[8])), note=row[9], ask_s=row[10], eval_s=row[11], reevaluates=row[12],
    )


def _insert_candidate(db: sqlite3.Connection, c: Candidate) -> None:
    """Insert the candidate ``c`` into ``candidates``, stamped now (IntegrityError when its index is taken)."""
    db.execute(
        "INSERT INTO candidates (idx, iteration, source, params, params_enc, feedback, feedback_enc, clipped, seeds, note,"
        " created, ask_s, eval_s, reevaluates) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (
            c.index, c.iteration, c.source,
            json.dumps([float(v) for v in c.params]), json.dumps([float(v) for v in c.params_enc]),
            json.dumps(c.feedback.to_json()), json.dumps(c.feedback_enc.to_json()),
            c.clipped, json.dumps(list(c.seeds)), c.note, time.time(), c.ask_s, c.eval_s, c.reevaluates,
        ),
    )


def _llm_call(columns: list[str], row: Any) -> dict[str, Any]:
    """One ``llm_calls`` row as a dict by column name, ``ok`` and ``answered`` as bools and ``decisions`` parsed."""
    d = dict(zip(columns, row))
    d["ok"] = bool(d["ok"])
    d["answered"] = bool(d["answered"])
    d["decisions"] = json.loads(d["decisions"]) if d["decisions"] else None
    return d


def _exchange_values(ex: Any) -> tuple[Any, ...]:
    """What an ``Exchange`` (or an older exchange-like object, without error_kind, retry or
    answer_source) holds for its ``llm_calls`` row: request, response, content, reasoning,
    prompt_chars, prompt_tokens, completion_tokens, latency_s, ok, error, error_kind, retry,
    answer_source, in this order."""
    return (ex.request, ex.response, ex.content, ex.reasoning, ex.prompt_chars, ex.prompt_tokens, ex.completion_tokens,
            ex.latency_s, int(ex.ok), ex.error, getattr(ex, "error_kind", None), int(getattr(ex, "retry", 0)),
            getattr(ex, "answer_source", None))


def _decisions_json(decisions: Mapping[str, Any] | None) -> str | None:
    """The ``llm_calls.decisions`` text of a form's public choices (None: none recorded)."""
    return None if decisions is None else json.dumps(dict(decisions))


def _log_adaptation(db: sqlite3.Connection, iteration: int, attempt: int, change: str) -> None:
    """Append one change of the LLM client's requests to ``llm_adaptations``."""
    row = db.execute("SELECT value FROM meta WHERE key = 'llm_adaptations'").fetchone()
    log = json.loads(row[0]) if row else []
    log.append({"iteration": iteration, "attempt": attempt, "change": change, "created": time.time()})
    db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('llm_adaptations', ?)", (json.dumps(log),))


class RunStore:
    """The store of one run: ``run.sqlite`` in the run directory (SQLite, WAL).

    Use it as a context manager, which closes the connection however the block ends::

        with open_store(run_dir) as store:
            config = store.config()

    Reads return plain values (``Candidate``, ``FinalEval``, dicts); every write is one
    transaction (``BEGIN IMMEDIATE``), so concurrent writers queue rather than fail and a crash
    leaves each row whole or absent. Every SQLite failure is a one-line ``StoreError``.

    Args:
        path: the database file; created (with its schema) when missing, migrated when older.

    Raises:
        StoreError: the file cannot be opened, is not a SQLite database, has a newer schema, or
            stays locked past ``BUSY_TIMEOUT_S``.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.RLock()
        try:
            # one connection, shared by the threads of a process (requests in flight at once): ``_lock``
            # serialises its use, so each transaction is one thread's
            self._db = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as e:
            raise StoreError(f"run store {self.path} cannot be opened ({e})") from None
        try:
            enable_wal(self._db, BUSY_TIMEOUT_S)
            self._db.execute("PRAGMA synchronous=NORMAL")
            with self._tx() as db:  # one writer creates or migrates; the others wait for it
                create_or_migrate(db, self.path)
        except StoreError:
            self._db.close()
            raise
        except sqlite3.DatabaseError as e:
            self._db.close()
            raise StoreError(f"run store {self.path} is not a readable SQLite database ({e})") from None

    # -- plumbing -------------------------------------------------------------------------
    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction, taken up front (BEGIN IMMEDIATE) so concurrent writers queue
        on the busy timeout instead of failing on a lock upgrade. SQLite errors become StoreError;
        IntegrityError passes through for the caller to word. Other threads of this process wait
        for it to end (the connection's lock)."""
        with self._lock:
            try:
                self._db.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as e:
                raise StoreError(_describe(e, self.path)) from None
            try:
                yield self._db
                self._db.execute("COMMIT")
            except BaseException as e:
                if self._db.in_transaction:
                    try:
                        self._db.execute("ROLLBACK")
                    except sqlite3.Error:
                        pass  # SQLite already rolled back (e.g. after SQLITE_FULL)
                if isinstance(e, sqlite3.Error) and not isinstance(e, sqlite3.IntegrityError):
                    raise StoreError(_describe(e, self.path)) from None
                raise

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> _Rows:
        """The rows of one query, read whole under the connection's lock."""
        with self._lock:
            try:
                cur = self._db.execute(sql, args)
                return _Rows(cur.fetchall(), cur.description)
            except sqlite3.Error as e:
                raise StoreError(_describe(e, self.path)) from None

    def _meta(self, key: str) -> str | None:
        row = self._read("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def _set_meta(self, key: str, value: str) -> None:
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, value))

    def schema_version(self) -> int:
        """The schema version the file holds (``SCHEMA_VERSION`` once opened by this version)."""
        return int(self._meta("schema_version") or 0)

    def integrity_check(self) -> str:
        """SQLite's own verdict on the file: 'ok' or the first problems found."""
        rows = self._read("PRAGMA integrity_check").fetchall()
        return "; ".join(str(r[0]) for r in rows)

    def close(self) -> None:
        """Close the connection (the last one to close checkpoints the WAL into the database file)."""
        with self._lock:
            self._db.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- run-level ------------------------------------------------------------------------
    def init_run(self, run_id: str, config: dict[str, Any], key_fingerprint: str, *, keyed_streams: bool = False) -> None:
        """Record a new run: its id, its config (``RunConfig.to_json()`` or an RL baseline's), the
        fingerprint of its secrets, status ``running``, and (``keyed_streams``) that its random
        streams are keyed by its secrets (``seeding.Streams``). Raises StoreError if a run is already there."""
        if self._meta("run_id") is not None:
            raise StoreError(f"{self.path} already holds run {self._meta('run_id')}")
        rows = [("run_id", run_id), ("config", json.dumps(config)), ("key_fingerprint", key_fingerprint),
                ("status", RunStatus.RUNNING.value), ("created", str(time.time()))]
        if keyed_streams:
            rows.append(("streams", "keyed"))
        with self._tx() as db:
            for k, v in rows:
                db.execute("INSERT INTO meta (key, value) VALUES (?, ?)", (k, v))

    def run_id(self) -> str:
        """The run's id; StoreError when the store holds no run."""
        rid = self._meta("run_id")
        if rid is None:
            raise StoreError(f"{self.path} holds no run")
        return rid

    def config(self) -> dict[str, Any]:
        """The stored configuration as JSON (``RunConfig.from_json`` reads a search's; an RL
        baseline's carries ``"kind": "rl"``). StoreError when there is none."""
        raw = self._meta("config")
        if raw is None:
            raise StoreError(f"{self.path} holds no run configuration")
        return dict(json.loads(raw))

    def change_config(self, config: dict[str, Any], change: dict[str, Any] | None = None) -> None:
        """Replace the stored config and append ``change`` (if any) to ``endpoint_changes``, in one transaction."""
        changes = self.endpoint_changes() + ([change] if change is not None else [])
        with self._tx() as db:
            db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('config', ?)", (json.dumps(config),))
            db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('endpoint_changes', ?)", (json.dumps(changes),))

    def endpoint_changes(self) -> list[dict[str, Any]]:
        """LLM endpoint changes made by ``ppprops resume --base-url/--model/--api-key-env``, oldest first."""
        raw = self._meta("endpoint_changes")
        return list(json.loads(raw)) if raw else []

    def streams_keyed(self) -> bool:
        """True when the run's random streams are keyed by its secrets (``seeding.Streams``); runs
        recorded before streams were keyed derive them from the run seed alone."""
        return self._meta("streams") == "keyed"

    def key_fingerprint(self) -> str:
        """The fingerprint of the run's secrets (``Secrets.fingerprint``); "" when none is stored."""
        return self._meta("key_fingerprint") or ""

    def status(self) -> str:
        """The stored status text: ``running``, ``finished``, ``stopped: <reason>``, ``interrupted``
        (``RunStatus.parse`` splits it), or ``unknown`` when none is stored."""
        return self._meta("status") or RunStatus.UNKNOWN.value

    def run_status(self) -> tuple[RunStatus, str]:
        """``(status, reason)``; the reason is empty unless the run stopped on purpose."""
        return RunStatus.parse(self.status())

    def set_status(self, status: RunStatus, reason: str = "") -> None:
        """Record where the run stands; ``reason`` goes with ``RunStatus.STOPPED``."""
        self._set_meta("status", RunStatus(status).stored(reason))

    # -- candidates -----------------------------------------------------------------------
    def add_candidate(self, c: Candidate) -> None:
        """Record one evaluated candidate in its own transaction; StoreError if its index is taken."""
        try:
            with self._tx() as db:
                _insert_candidate(db, c)
        except sqlite3.IntegrityError:
            raise StoreError(f"candidate {c.index} is already recorded in {self.path}") from None

    def record_trial(self, c: Candidate) -> None:
        """Record the told candidate of the pending trial ``c.index`` and clear that trial, in one
        transaction. StoreError if no such trial is pending or its candidate is already recorded."""
        try:
            with self._tx() as db:
                gone = db.execute("DELETE FROM pending WHERE idx = ?", (c.index,)).rowcount
                if not gone:
                    raise StoreError(f"trial {c.index} is not pending in {self.path}")
                _insert_candidate(db, c)
        except sqlite3.IntegrityError:
            raise StoreError(f"candidate {c.index} is already recorded in {self.path}") from None

    # -- the pending trials ---------------------------------------------------------------
    def add_pending(self, t: Trial, *, limit: int = 1) -> None:
        """Store a trial a study has asked for (before ``ask`` returns it), held by ``t.worker``.
        StoreError when ``limit`` trials are already pending (``--parallel``; 1: one at a time) or
        its number is already a recorded candidate, a failed trial or a pending one."""
        self.add_pending_many([t], limit=limit)

    def add_pending_many(self, trials: list[Trial], *, limit: int = 1, queued: list[dict[str, Any]] | None = None) -> None:
        """Store several asked trials in one transaction (a round of ``--parallel P``): all or none;
        with ``queued``, the queue of given policies left after them (``queued``) in the same one."""
        try:
            with self._tx() as db:
                if queued is not None:
                    db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('queued', ?)", (json.dumps(queued),))
                for t in trials:
                    if db.execute("SELECT 1 FROM candidates WHERE idx = ?", (t.number,)).fetchone():
                        raise StoreError(f"candidate {t.number} is already recorded in {self.path}")
                    if db.execute("SELECT 1 FROM failed WHERE idx = ?", (t.number,)).fetchone():
                        raise StoreError(f"trial {t.number} is already recorded as failed in {self.path}")
                    out = db.execute("SELECT idx FROM pending ORDER BY idx").fetchall()
                    if len(out) >= limit:
                        if limit == 1:
                            raise StoreError(f"trial {out[0][0]} is already pending in {self.path}")
                        raise StoreError(f"{len(out)} trials are already pending in {self.path} (at most {limit} at once)")
                    _insert_pending(db, t)
        except sqlite3.IntegrityError:
            raise StoreError(f"a trial of {[t.number for t in trials]} is already pending in {self.path}") from None

    def pending_trial(self) -> Trial | None:
        """The first trial asked for and not yet told (lowest number), or None."""
        trials = self.pending_trials()
        return trials[0] if trials else None

    def pending_trials(self) -> list[Trial]:
        """Every trial asked for and not yet told, by number, each with the worker holding it
        (``Trial.worker``: "" for a trial asked without a worker name, None for one nobody holds
        yet: the rest of a round, or a failed trial asked again)."""
        rows = self._read(f"SELECT {_TRIAL_COLUMNS} FROM pending ORDER BY idx").fetchall()
        return [_trial(r) for r in rows]

    def assign(self, number: int, worker: str) -> None:
        """Hand the pending trial ``number`` to ``worker`` (a name; "" the unnamed worker); StoreError when it is not pending."""
        with self._tx() as db:
            if not db.execute("UPDATE pending SET worker = ? WHERE idx = ?", (worker, int(number))).rowcount:
                raise StoreError(f"trial {number} is not pending in {self.path}")

    # -- failed trials --------------------------------------------------------------------
    def fail_trial(self, number: int, reason: str) -> None:
        """Move the pending trial ``number`` to the failed trials with ``reason``, in one
        transaction; StoreError when it is not pending. A failed trial is no candidate: no
        proposer, prompt or selection ever sees it."""
        with self._tx() as db:
            row = db.execute(f"SELECT {_TRIAL_COLUMNS} FROM pending WHERE idx = ?", (int(number),)).fetchone()
            if row is None:
                raise StoreError(f"trial {number} is not pending in {self.path}")
            db.execute("DELETE FROM pending WHERE idx = ?", (int(number),))
            db.execute(
                "INSERT INTO failed (idx, phase, iteration, source, params, seeds, clipped, note, ask_s, n_s, n_a, reevaluates,"
                " worker, reason, created) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (*row, reason, time.time()),
            )

    def failed_trials(self) -> list[tuple[Trial, str]]:
        """Every failed trial, by number, with its reason."""
        rows = self._read(f"SELECT {_TRIAL_COLUMNS}, reason FROM failed ORDER BY idx").fetchall()
        return [(_trial(r[:13]), str(r[13])) for r in rows]

    def retry_trial(self, number: int, *, limit: int = 1) -> Trial:
        """Move the failed trial ``number`` back to the pending trials (held by nobody), with the
        same parameters and seeds; returns it. StoreError when it did not fail or ``limit`` trials
        are already pending."""
        with self._tx() as db:
            row = db.execute(f"SELECT {_TRIAL_COLUMNS} FROM failed WHERE idx = ?", (int(number),)).fetchone()
            if row is None:
                raise StoreError(f"trial {number} did not fail in {self.path}")
            (out,) = db.execute("SELECT COUNT(*) FROM pending").fetchone()
            if out >= limit:
                raise StoreError(f"{out} trial(s) are pending in {self.path} (at most {limit} at once): tell one first")
            trial = replace(_trial(row), worker=None)
            db.execute("DELETE FROM failed WHERE idx = ?", (int(number),))
            _insert_pending(db, trial)
            return trial

    def next_number(self) -> int:
        """The number the next new trial gets: one past every recorded, failed or pending one."""
        row = self._read("SELECT MAX(m) FROM (SELECT MAX(idx) AS m FROM candidates UNION ALL SELECT MAX(idx) FROM pending"
                         " UNION ALL SELECT MAX(idx) FROM failed)").fetchone()
        return 0 if row[0] is None else int(row[0]) + 1

    def trial_state(self, number: int) -> str | None:
        """Where trial ``number`` stands: ``told`` (a recorded candidate), ``failed``, ``pending``, or None (never asked)."""
        for table, state in (("candidates", "told"), ("failed", "failed"), ("pending", "pending")):
            if self._read(f"SELECT 1 FROM {table} WHERE idx = ?", (int(number),)).fetchone():
                return state
        return None

    def failed_count(self) -> int:
        """How many trials failed (and were not retried)."""
        return int(self._read("SELECT COUNT(*) FROM failed").fetchone()[0])

    def candidate_count(self) -> int:
        """How many candidates are recorded."""
        return int(self._read("SELECT COUNT(*) FROM candidates").fetchone()[0])

    def candidates(self, since: int = 0) -> list[Candidate]:
        """Every recorded candidate from index ``since`` on, by index (``params`` and ``params_enc``:
        float64 arrays of shape (D,))."""
        rows = self._read(f"SELECT {_CANDIDATE_COLUMNS} FROM candidates WHERE idx >= ? ORDER BY idx", (int(since),)).fetchall()
        return [_candidate(r) for r in rows]

    def candidate_times(self) -> list[tuple[int, str, int, float, float | None, float | None]]:
        """(index, source, iteration, created, ask_s, eval_s) per candidate: when each was
        recorded and where its time went, for the overhead benchmark and progress reports."""
        return [tuple(r) for r in self._read(  # type: ignore[misc]
            "SELECT idx, source, iteration, created, ask_s, eval_s FROM candidates ORDER BY idx").fetchall()]

    # -- LLM exchanges --------------------------------------------------------------------
    def begin_llm_call(self, iteration: int, attempt: int, request: str, *, prompt_chars: int, retry: int = 0, form: str,
                       decisions: Mapping[str, Any] | None = None) -> int:
        """Write one try ahead, before its bytes leave: ``request`` is the body about to be sent.
        Until ``complete_llm_call`` it reads as an unanswered try (``answered`` false, not ``ok``,
        error kind ``unanswered``), and so it stays if the process ends first. ``created`` is when
        it was written, i.e. when it left (also its ``sent``). Returns its row id."""
        now = time.time()
        with self._tx() as db:
            cur = db.execute(
                "INSERT INTO llm_calls (iteration, attempt, request, prompt_chars, latency_s, ok, error, created, error_kind, retry,"
                " form, decisions, answered, sent) VALUES (?, ?, ?, ?, 0.0, 0, ?, ?, ?, ?, ?, ?, 0, ?)",
                (iteration, attempt, request, prompt_chars, UNANSWERED_ERROR, now, UNANSWERED, int(retry), form,
                 _decisions_json(decisions), now),
            )
            return int(cur.lastrowid or 0)

    def complete_llm_call(self, call_id: int, ex: Any) -> None:
        """Complete the try ``call_id`` written ahead with what came back (an ``Exchange``, failed
        or not; its ``request`` replaces the one written ahead, which it equals for the endpoint
        client), and append its adaptation to ``llm_adaptations``, in one transaction.

        Raises:
            StoreError: no try ``call_id`` is waiting for its answer.
        """
        adaptation = getattr(ex, "adaptation", None)
        with self._tx() as db:
            row = db.execute("SELECT iteration, attempt FROM llm_calls WHERE id = ? AND answered = 0", (int(call_id),)).fetchone()
            if row is None:
                raise StoreError(f"LLM call {call_id} is not waiting for its answer in {self.path}")
            if adaptation:
                _log_adaptation(db, row[0], row[1], adaptation)
            db.execute(
                "UPDATE llm_calls SET request = ?, response = ?, content = ?, reasoning = ?, prompt_chars = ?, prompt_tokens = ?,"
                " completion_tokens = ?, latency_s = ?, ok = ?, error = ?, error_kind = ?, retry = ?, answer_source = ?,"
                " answered = 1 WHERE id = ? AND answered = 0",
                (*_exchange_values(ex), int(call_id)),
            )

    def add_llm_call(self, iteration: int, attempt: int, ex: Any, parse_error: str | None, *, form: str,
                     decisions: Mapping[str, Any] | None = None) -> int:
        """One HTTP try, failed or not: ``ex`` is an ``Exchange`` (its error_kind, retry,
        answer_source and adaptation are optional, so older exchange-like objects still record),
        ``form`` the prompt form that built it and ``decisions`` the public choices the form made
        (``wire.forms``). An adaptation is appended to ``llm_adaptations`` in the same
        transaction. Returns the call's row id (``annotate_llm_call``)."""
        adaptation = getattr(ex, "adaptation", None)
        with self._tx() as db:
            if adaptation:
                _log_adaptation(db, iteration, attempt, adaptation)
            cur = db.execute(
                "INSERT INTO llm_calls (iteration, attempt, request, response, content, reasoning, prompt_chars,"
                " prompt_tokens, completion_tokens, latency_s, ok, error, error_kind, retry, answer_source, parse_error,"
                " created, form, decisions) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (iteration, attempt, *_exchange_values(ex), parse_error, time.time(), form, _decisions_json(decisions)),
            )
            return int(cur.lastrowid or 0)

    def annotate_llm_call(self, call_id: int, *, parse_error: str | None, answer_source: str | None) -> None:
        """Add the proposer's verdict on the recorded answer ``call_id``: why it could not be used
        (``parse_error``, None when it was) and where the proposal was read (``content`` or ``reasoning``)."""
        with self._tx() as db:
            db.execute("UPDATE llm_calls SET parse_error = ?, answer_source = ? WHERE id = ?", (parse_error, answer_source, int(call_id)))

    def llm_adaptations(self) -> list[dict[str, Any]]:
        """Changes the LLM client made to its requests, in order: {iteration, attempt, change, created}."""
        raw = self._meta("llm_adaptations")
        return list(json.loads(raw)) if raw else []

    def begin_llm_session(self) -> None:
        """Note that a new LLM client starts here (a run's start or a resume): its requests start
        from the configured shape again and adapt anew. Kept in the ``meta`` key ``llm_sessions``
        as the number of LLM calls recorded before it, so the audit replays each session's client."""
        with self._tx() as db:
            (n,) = db.execute("SELECT COUNT(*) FROM llm_calls").fetchone()
            row = db.execute("SELECT value FROM meta WHERE key = 'llm_sessions'").fetchone()
            starts = json.loads(row[0]) if row else []
            if not starts or starts[-1] != n:
                starts.append(n)
                db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('llm_sessions', ?)", (json.dumps(starts),))

    def pacing_state(self) -> dict[str, Any]:
        """The request pacer's state (``llm.pacing.Pacer``), shared by the processes that drive
        one study: {} before the first paced request."""
        raw = self._meta("pacing")
        return dict(json.loads(raw)) if raw else {}

    def set_pacing_state(self, state: Mapping[str, Any]) -> None:
        """Replace the request pacer's state."""
        self._set_meta("pacing", json.dumps(dict(state)))

    def queued(self) -> list[dict[str, Any]]:
        """The given policies waiting to be the next new trials (``warm_start.enqueue``), oldest first."""
        raw = self._meta("queued")
        return list(json.loads(raw)) if raw else []

    def set_queued(self, queued: list[dict[str, Any]]) -> None:
        """Replace the queue of given policies."""
        self._set_meta("queued", json.dumps(queued))

    def stop_state(self) -> dict[str, Any]:
        """The stop rules' state (``stopping.StopState``): where the search ended early and why,
        and the search's clock; {} before the first check."""
        raw = self._meta("stop")
        return dict(json.loads(raw)) if raw else {}

    def set_stop_state(self, state: Mapping[str, Any]) -> None:
        """Replace the stop rules' state."""
        self._set_meta("stop", json.dumps(dict(state)))

    def llm_sessions(self) -> list[int] | None:
        """Where each LLM client session began, as a count of the calls before it (ascending);
        None for runs recorded before sessions were (then only endpoint changes are known)."""
        raw = self._meta("llm_sessions")
        return [int(n) for n in json.loads(raw)] if raw else None

    def llm_calls(self) -> list[dict[str, Any]]:
        """Every recorded HTTP try, in the order sent, as dicts with the ``llm_calls`` columns
        (request and response bodies as sent and received, tokens, latency in seconds, ok, errors,
        ``answered`` (false: written ahead and never completed), ``sent``: when it left, in Unix
        seconds (None for calls recorded before requests were written ahead: their ``created``
        is when the answer came))."""
        cur = self._read(f"SELECT {_LLM_CALL_COLUMNS} FROM llm_calls ORDER BY id")
        cols = [d[0] for d in cur.description]
        return [_llm_call(cols, row) for row in cur.fetchall()]

    # -- final evaluation -----------------------------------------------------------------
    def set_final_eval(self, fe: FinalEval) -> None:
        """Record (or replace) the final evaluation."""
        with self._tx() as db:
            db.execute(
                "INSERT OR REPLACE INTO final_eval (id, candidate_idx, returns, seeds, created) VALUES (1, ?, ?, ?, ?)",
                (fe.candidate_index, json.dumps(list(fe.returns)), json.dumps(list(fe.seeds)), time.time()),
            )

    def final_eval(self) -> FinalEval | None:
        """The final evaluation, or None before it ran."""
        row = self._read("SELECT candidate_idx, returns, seeds FROM final_eval WHERE id = 1").fetchone()
        if row is None:
            return None
        return FinalEval(candidate_index=row[0], returns=tuple(json.loads(row[1])), seeds=tuple(json.loads(row[2])))


def open_store(run_dir: Path, *, create: bool = False) -> RunStore:
    """The store of ``run_dir`` (use it in a ``with`` block).

    Raises:
        StoreError: ``run_dir`` holds no ``run.sqlite`` (unless ``create``), or it cannot be opened.
    """
    path = Path(run_dir) / DB_NAME
    if not create and not path.exists():
        raise StoreError(f"{run_dir} is not a ppprops run directory (no {DB_NAME})")
    return RunStore(path)

