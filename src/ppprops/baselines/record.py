"""What an RL baseline run leaves in its ``run.sqlite``, and how ``ppprops show`` reads it back.

The RunStore schema describes searches (candidates, LLM calls). An RL run has neither, so the store
keeps only its config (with ``"kind": "rl"``), its status and its final evaluation, and the
episodes finished during training go to two tables of their own, created here in the same file.
No torch import: showing a run must work without the ``rl`` extra.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ConfigError, StoreError
from ..status import RunKind
from ..store import DB_NAME, RunStore

KIND = RunKind.RL.value  # the stored config's "kind"
MODEL_NAME = "model.zip"
# A FinalEval belongs to a candidate; an RL run's belongs to the trained model, which is none.
NO_CANDIDATE = -1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS rl_episodes (
    idx INTEGER PRIMARY KEY,
    timestep INTEGER NOT NULL,
    ret REAL NOT NULL,
    length INTEGER NOT NULL,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS rl_info (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


@dataclass(frozen=True)
class TrainingEpisode:
    """One episode finished during training (stochastic actions, exploration included)."""

    index: int
    timestep: int  # agent timesteps done when it ended
    ret: float
    length: int


class TrainingLog:
    """The RL tables of one run.sqlite, on a connection of their own (WAL lets it share the file).

    ``db_path`` is the run's ``run.sqlite``; the tables are created if missing. Use it in a ``with``
    block (or call ``close``). Raises StoreError when the file is not a readable SQLite database.
    """

    def __init__(self, db_path: Path) -> None:
        self.path = Path(db_path)
        try:
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as e:
            raise StoreError(f"run store {self.path} is not a readable SQLite database ({e})") from None

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def add_episodes(self, episodes: Sequence[TrainingEpisode]) -> None:
        """Many episodes per transaction: CartPole finishes hundreds a second early in training."""
        if not episodes:
            return
        now = time.time()
        with self._tx() as db:
            db.executemany(
                "INSERT INTO rl_episodes (idx, timestep, ret, length, created) VALUES (?, ?, ?, ?, ?)",
                [(e.index, e.timestep, e.ret, e.length, now) for e in episodes],
            )

    def episodes(self) -> list[TrainingEpisode]:
        """Every recorded training episode, in the order they finished (by ``index``); [] for none."""
        rows = self._db.execute("SELECT idx, timestep, ret, length FROM rl_episodes ORDER BY idx").fetchall()
        return [TrainingEpisode(index=r[0], timestep=r[1], ret=r[2], length=r[3]) for r in rows]

    def set_info(self, **values: Any) -> None:
        """Store (or replace) each keyword as one ``rl_info`` entry, JSON-encoded, in one transaction.

        The run records ``timesteps_done`` (agent steps) and ``wall_s`` (training time, seconds)
        here. A value JSON cannot encode raises TypeError and nothing of the call is stored.
        """
        with self._tx() as db:
            for k, v in values.items():
                db.execute("INSERT OR REPLACE INTO rl_info (key, value) VALUES (?, ?)", (k, json.dumps(v)))

    def info(self) -> dict[str, Any]:
        """Every ``rl_info`` entry, JSON-decoded; {} before training has ended."""
        return {k: json.loads(v) for k, v in self._db.execute("SELECT key, value FROM rl_info").fetchall()}

    def close(self) -> None:
        """Close the connection."""
        self._db.close()

    def __enter__(self) -> TrainingLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def is_rl_config(config: dict[str, Any]) -> bool:
    """True for the stored config of an RL baseline run (``RunKind.of_config``)."""
    return RunKind.of_config(config) is RunKind.RL


def rl_summary(store: RunStore) -> dict[str, Any]:
    """The ``show --json`` object of an RL run: the search summary's keys, plus ``training``.

    ``candidates`` and ``llm_calls`` are empty and ``best`` is null: no candidate policy was
    searched, and the trained model's score is ``final_eval`` (the number the paper's baseline
    table reports), so nothing needs to read ``best`` to compare an RL run with a search.
    """
    config = store.config()
    fe = store.final_eval()
    with TrainingLog(store.path) as log:
        episodes, info = log.episodes(), log.info()
    return {
        "run_id": store.run_id(),
        "status": store.status(),
        "env": config["task"],
        "method": config["method"],
        "mechanisms": None,
        "seed": config["seed"],
        "config": config,
        "best": None,
        "final_eval": {"mean": fe.mean, "std": fe.std, "episodes": len(fe.returns), "returns": list(fe.returns)} if fe is not None and fe.returns else None,
        "counts": dict.fromkeys(("candidates", "warmup", "llm", "fallback", "clipped_candidates", "llm_calls"), 0) | {"answer_failures": {}},
        "candidates": [],
        "llm_calls": [],
        "training": {
            "timesteps": config["timesteps"],
            "timesteps_done": info.get("timesteps_done"),
            "wall_s": info.get("wall_s"),
            "model": MODEL_NAME if (store.path.parent / MODEL_NAME).exists() else None,
            "episodes": [{"index": e.index, "timestep": e.timestep, "return": e.ret, "length": e.length} for e in episodes],
        },
    }


def format_rl_summary(s: dict[str, Any]) -> str:
    """The text ``ppprops show`` prints for an RL run."""
    t = s["training"]
    eps = t["episodes"]
    lines = [
        f"run      {s['run_id']} ({s['status']})",
        f"task     {s['env']}   method {s['method']}   seed {s['seed']}",
    ]
    done = f"{t['timesteps_done']} done" if t["timesteps_done"] is not None else "not finished"
    wall = f" in {t['wall_s']:.1f} s" if t["wall_s"] is not None else ""
    train = f"training {t['timesteps']} timesteps ({done}){wall}; {len(eps)} episode{'' if len(eps) == 1 else 's'}"
    if eps:
        last = [e["return"] for e in eps[-20:]]
        train += f", mean return of the last {len(last)} {sum(last) / len(last):.2f}"
    lines.append(train)
    if s["final_eval"]:
        fe = s["final_eval"]
        lines.append(f"final    {fe['mean']:.2f} +- {fe['std']:.2f} over {fe['episodes']} fresh episodes (deterministic actions)")
    if t["model"]:
        lines.append(f"model    {t['model']}")
    return "\n".join(lines)


def refuse_resume(run_dir: Path) -> None:
    """``ppprops resume`` continues searches; an RL run (finished or not) gets one line, not a traceback.

    Returns quietly when ``run_dir`` holds no store, or one that cannot be read (resume reports those
    itself), or a search run.

    Raises:
        ConfigError: ``run_dir`` is an RL baseline run.
    """
    path = Path(run_dir) / DB_NAME
    if not path.is_file():
        return  # resume reports missing or foreign directories itself
    try:
        with RunStore(path) as store:
            config = store.config()
    except StoreError:
        return  # a corrupt or empty store: resume says so itself
    if is_rl_config(config):
        raise ConfigError(f"{run_dir} is an RL baseline run ({config['method']}); it cannot be resumed: "
                          "start a new one with 'ppprops baseline rl'")  # fmt: skip
