"""Run directories: making one atomically, opening one, and the final evaluation's episodes.

A run directory holds ``run.sqlite`` (the store), ``secrets.key`` (mode 0600) and, once
finished, ``best_policy.json``.

Crash safety: the directory is built under a temporary name and renamed into place, so a run
killed while starting leaves either nothing at ``--out`` or a complete, resumable directory.
After that every step is a committed store row or an atomic file rename, so a study reopened after
a ``kill -9`` at any moment finishes with each candidate recorded once.
"""

from __future__ import annotations

import errno
import os
import shutil
import uuid
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import naming
from .client.hardening import generate_secrets
from .client.secrets import Secrets
from .config import RunConfig
from .errors import ConfigError, StoreError
from .evaluation import Evaluator, check_parallel
from .events import NO_EVENTS, RunEvents
from .store import DB_NAME, KEY_NAME, RunStore, open_store


def new_run_id(config: RunConfig) -> str:
    """A fresh run id, ``<task>__<method>__<seed>__<time>-<4 hex digits>`` (``naming.new_run_id``)."""
    return naming.new_run_id(config.task, config.method, config.seed)


def create_run(config: RunConfig, run_dir: Path, secrets: Secrets | None = None) -> tuple[RunStore, Secrets]:
    """Make the directory, key file and store. Refuses a directory that already holds something.

    ``secrets`` is for tests and controlled experiments; normally they are drawn fresh here.
    Everything is written under a temporary sibling name first, then renamed to ``run_dir``.
    The stored config holds the task's whole declaration (``task_spec``), so the run can be resumed
    and evaluated in any process; a task's env and info keys are checked before anything is written.
    """
    config.validate()
    task = config.make_task()
    if config.task_spec is None and task.spec is not None:
        config = replace(config, task_spec=task.spec.model_dump(mode="json"))
    if config.workers > 1:
        check_parallel(task)  # before the directory: a pool that could never start
    run_dir = Path(run_dir)
    check_out(run_dir)
    prefix = f"{naming.safe_name(config.task)}__{config.method}__{config.seed}__"
    if secrets is not None:
        run_id = secrets.run_id
    elif run_dir.name.startswith(prefix):  # a default-named directory (naming.default_run_dir): its name is the id
        run_id = run_dir.name
    else:
        run_id = new_run_id(config)
    if secrets is None:
        secrets = generate_secrets(run_id, task, config.encoding)  # paper secrets, plus offsets/warp when hardened
    elif len(secrets.a) != task.D:
        raise ConfigError(f"given secrets have D={len(secrets.a)}, task {task.name} needs {task.D}")
    tmp = run_dir.parent / f".{run_dir.name}.{uuid.uuid4().hex[:8]}.creating"
    try:
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as e:
        raise ConfigError(f"cannot create output directory {run_dir}: {e.strerror}") from None
    try:
        try:
            secrets.save(tmp / KEY_NAME)
        except OSError as e:
            raise StoreError(f"cannot write the key file in {run_dir}: {e.strerror}") from None
        with RunStore(tmp / DB_NAME) as store:  # closed (the WAL checkpointed) before the directory moves
            store.init_run(run_id, config.to_json(), secrets.fingerprint(), keyed_streams=True)
        try:
            os.rename(tmp, run_dir)  # onto a missing or empty directory, atomically
        except OSError as e:
            if e.errno in (errno.ENOTEMPTY, errno.EEXIST):
                raise ConfigError(f"output directory {run_dir} was filled meanwhile; choose a new --out") from None
            raise StoreError(f"cannot create output directory {run_dir}: {e.strerror}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return open_store(run_dir), secrets


def check_out(run_dir: Path) -> None:
    """Refuse, in one ConfigError line, an output directory a new run cannot be made in: a file, a
    directory that already holds something (another run, or other files)."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"--out {run_dir} is a file, not a directory; choose a new --out")
    if run_dir.is_dir() and any(run_dir.iterdir()):
        what = "another run" if (run_dir / DB_NAME).exists() else "files"
        raise ConfigError(f"output directory {run_dir} already holds {what}; choose a new --out or use 'ppprops resume'")


def load_run(run_dir: Path) -> tuple[RunStore, RunConfig, Secrets]:
    """The open store, config and secrets of a run directory; the caller closes the store
    (``with store:``). Nothing stays open when this raises.

    Raises:
        StoreError: not a run directory, or a damaged store.
        KeyFileError: the key file is missing, damaged, or belongs to another run.
        ConfigError: the stored config names a task that cannot be made here.
    """
    store = open_store(run_dir)
    try:
        config = RunConfig.from_json(store.config())
        task = config.make_task()
        secrets = Secrets.load(Path(run_dir) / KEY_NAME, run_id=store.run_id(), D=task.D, fingerprint=store.key_fingerprint())
    except BaseException:
        store.close()
        raise
    return store, config, secrets


def final_returns(evaluator: Evaluator, theta: np.ndarray, seeds: Sequence[int], events: RunEvents = NO_EVENTS) -> tuple[float, ...]:
    """Episode returns of ``theta`` on ``seeds``, in order, reported to ``events`` as they come.

    Episodes run in chunks of ``evaluator.workers`` (one per worker at a time); each episode
    depends only on its seed, so the returns equal one ``evaluate(theta, seeds)`` call.
    """
    if not seeds:
        return ()
    events.on_final_start(len(seeds))
    returns: list[float] = []
    chunk = max(1, evaluator.workers)
    for i in range(0, len(seeds), chunk):
        returns += evaluator.evaluate(theta, seeds[i : i + chunk]).episode_returns
        events.on_final_episode(len(returns))
    return tuple(returns)
