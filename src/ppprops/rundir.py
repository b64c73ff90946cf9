"""Run directories: making one atomically, reading one back (``open_run``), and the final evaluation's episodes.

A run directory holds ``run.sqlite`` (the store, ``DB_NAME``), ``secrets.key`` (mode 0600,
``KEY_NAME``) and, once finished, ``best_policy.json`` (``POLICY_NAME``). These names are defined
here (``DB_NAME`` in ``store``, which opens it) and nowhere else; every reader of a stored run
opens it with ``open_run``.

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
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np

from . import naming
from .client.secrets import Secrets
from .errors import ConfigError, KeyFileError, StoreError
from .events import NO_EVENTS, RunEvents
from .status import RunKind
from .store import DB_NAME, RunStore, open_store

if TYPE_CHECKING:  # imported where used: the names here and open_run cost no settings schema (ppprops ask)
    from .config import RunConfig
    from .evaluation import Evaluator
    from .tasks import Task

KEY_NAME = "secrets.key"  # the run's secrets (ppprops.client.secrets), mode 0600, beside the store
POLICY_NAME = "best_policy.json"  # the deployable policy (ppprops.policy_file), written when the run finishes


def new_run_id(config: RunConfig) -> str:
    """A fresh run id, ``<task>__<method>__<seed>__<time>-<4 hex digits>`` (``naming.new_run_id``)."""
    return naming.new_run_id(config.task, config.method, config.seed)


def create_run(config: RunConfig, run_dir: Path, secrets: Secrets | None = None) -> tuple[RunStore, Secrets]:
    """Make the directory, key file and store. Refuses a directory that already holds something.

    ``secrets`` is for tests and controlled experiments; normally they are drawn fresh here.
    Everything is written under a temporary sibling name first, then renamed to ``run_dir``.
    The stored config holds the task's whole declaration (``task_spec``), so the run can be resumed
    and evaluated in any process; a task's env and info keys are checked before anything is written,
    and so is what making its env needs first (a simulator extra, the modules it imports:
    ``Task.setup``).
    """
    from .client.hardening import generate_secrets
    from .evaluation import check_parallel

    config.validate()
    task = config.make_task()
    if task.has_env and task.setup is not None:
        task.setup()  # a missing extra says so now, not at the first episode of a directory already made
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


def missing_parents(run_dir: Path) -> list[Path]:
    """The folders above ``run_dir`` that do not exist yet (``create_run`` makes them), deepest first."""
    return [p for p in Path(run_dir).absolute().parents if not p.exists()]


def discard_empty_run(run_dir: Path, *, keep_dir: bool = False, parents: Sequence[Path] = ()) -> bool:
    """Remove the run directory ``run_dir`` when its store holds nothing of a search: no trial
    told, none failed, no LLM request, no final evaluation (a run refused in its first episode).
    Returns True when it was removed; a directory holding anything more, or none, is left as it is.

    The directory is first renamed to a hidden sibling, so it is gone at once under its own name;
    with ``keep_dir`` an empty directory is left in its place (one the user made for ``--out``).
    ``parents`` (``missing_parents`` before the run was made, deepest first) are removed too while
    they are empty.
    """
    run_dir = Path(run_dir)
    if not is_run_dir(run_dir):
        return False
    try:
        with RunStore(run_dir / DB_NAME) as store:
            empty = (store.candidate_count() == 0 and store.failed_count() == 0 and not store.llm_calls()
                     and store.final_eval() is None)  # fmt: skip
    except StoreError:
        return False
    if not empty:
        return False
    gone = run_dir.parent / f".{run_dir.name}.{uuid.uuid4().hex[:8]}.discarded"
    try:
        os.rename(run_dir, gone)
    except OSError:
        return False
    shutil.rmtree(gone, ignore_errors=True)
    if keep_dir:
        run_dir.mkdir(exist_ok=True)
    for folder in parents:
        try:
            folder.rmdir()
        except OSError:  # something else was put there meanwhile: it stays
            break
    return True


def check_out(run_dir: Path) -> None:
    """Refuse, in one ConfigError line, an output directory a new run cannot be made in: a file, a
    directory that already holds something (another run, or other files)."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"--out {run_dir} is a file, not a directory; choose a new --out")
    if run_dir.is_dir() and any(run_dir.iterdir()):
        what = "another run" if is_run_dir(run_dir) else "files"
        resume = (f" or continue it with 'ppprops resume {run_dir}' ('ppprops ask {run_dir}' for a study driven by ask/tell)"
                  if what == "another run" else "")
        raise ConfigError(f"output directory {run_dir} already holds {what}; choose a new --out{resume}")


def is_run_dir(path: Path) -> bool:
    """True when ``path`` holds a run's store (``DB_NAME``): a run or study directory."""
    return (Path(path) / DB_NAME).exists()


def policy_path(run_dir: Path) -> Path:
    """Where a run directory keeps its policy file (``POLICY_NAME``), whether or not it is there yet."""
    return Path(run_dir) / POLICY_NAME


class StoredRun:
    """A run directory opened for reading (``open_run``): its store, kind, configuration, task,
    secrets and policy file.

    ``store`` is open until the ``with`` block ends (or ``store.close()``); ``stored`` is the configuration
    as stored (JSON), ``kind`` the run's kind (a search or an RL baseline). ``config`` and ``task``
    are read on first use; ``secrets`` holds the key file's secrets once loaded (``open_run``'s
    ``secrets``, or ``load_secrets``), else None.
    """

    def __init__(self, path: Path, store: RunStore) -> None:
        self.path = path
        self.store = store
        self.stored: dict[str, Any] = store.config()
        self.kind = RunKind.of_config(self.stored)
        self.secrets: Secrets | None = None

    @cached_property
    def config(self) -> RunConfig:
        """The search's configuration, read back from the stored one (``RunConfig.from_json``).

        Raises:
            ConfigError: the stored configuration holds a key or value this version refuses.
        """
        from .config import RunConfig

        return RunConfig.from_json(self.stored)

    @cached_property
    def task(self) -> Task:
        """The task the search ran on, from its stored declaration (``RunConfig.make_task``).

        Raises:
            ConfigError: the stored configuration names a task that cannot be made here.
        """
        return self.config.make_task()

    @property
    def key_path(self) -> Path:
        """The run's key file (``KEY_NAME``)."""
        return self.path / KEY_NAME

    @property
    def policy_path(self) -> Path:
        """The run's policy file (``policy_path``); it exists once the run has finished."""
        return policy_path(self.path)

    @overload
    def load_secrets(self) -> Secrets: ...

    @overload
    def load_secrets(self, *, optional: bool) -> Secrets | None: ...

    def load_secrets(self, *, optional: bool = False) -> Secrets | None:
        """The run's secrets from its key file, checked against the store (run id, D, fingerprint);
        kept in ``secrets``. Loaded once: a second call returns the same secrets.

        ``optional``: a key file that is missing or does not load counts as absent (None), as the
        audit reads a run.

        Raises:
            KeyFileError: (not ``optional``) the key file is missing, damaged, or belongs to another run.
            ConfigError: the stored configuration names a task that cannot be made here (D comes
                from the task).
        """
        if self.secrets is not None:
            return self.secrets
        if optional and not self.key_path.exists():
            return None
        D = self.task.D
        try:
            self.secrets = Secrets.load(self.key_path, run_id=self.store.run_id(), D=D, fingerprint=self.store.key_fingerprint())
        except KeyFileError:
            if not optional:
                raise
        return self.secrets

    def __enter__(self) -> StoredRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.store.close()


def open_run(run_dir: Path | str, *, secrets: bool | Literal["optional"] = False) -> StoredRun:
    """The run in ``run_dir``, opened for reading; use it in a ``with`` block (it closes the store).
    Nothing stays open when this raises.

    ``secrets``: False reads no key file now (``StoredRun.load_secrets`` does, later); True loads
    the secrets now; ``"optional"`` loads them now when the key file is there and loads, else
    leaves ``secrets`` None (a key file that does not load counts as absent).

    Raises:
        StoreError: not a run directory, or a damaged store.
        KeyFileError: (``secrets=True``) the key file is missing, damaged, or belongs to another run.
        ConfigError: (with secrets) the stored config names a task that cannot be made here.
    """
    path = Path(run_dir)
    store = open_store(path)
    try:
        run = StoredRun(path, store)
        if secrets:
            run.load_secrets(optional=secrets == "optional")
    except BaseException:
        store.close()
        raise
    return run


def load_run(run_dir: Path) -> tuple[RunStore, RunConfig, Secrets]:
    """The open store, config and secrets of a run directory (``open_run`` with its secrets); the
    caller closes the store (``with store:``). Nothing stays open when this raises.

    Raises:
        StoreError: not a run directory, or a damaged store.
        KeyFileError: the key file is missing, damaged, or belongs to another run.
        ConfigError: the stored config names a task that cannot be made here.
    """
    run = open_run(run_dir, secrets=True)
    return run.store, run.config, run.load_secrets()


def find_runs(root: Path, *, recursive: bool = False, with_key: bool = False) -> list[Path]:
    """The run directories under ``root``, sorted: ``root`` itself, its children, and a grid's
    ``runs/*`` (``recursive``: at any depth). A directory holding ``run.sqlite`` is a run; with
    ``with_key`` only those that also hold their key file count. Directories whose name starts
    with ``.`` (a run still being created) are left out.

    Raises:
        ConfigError: ``root`` is not a directory.
    """
    root = Path(root)
    if not root.is_dir():
        raise ConfigError(f"{root} is not a directory")
    patterns = (f"**/{DB_NAME}",) if recursive else (DB_NAME, f"*/{DB_NAME}", f"runs/*/{DB_NAME}")
    found = {p.parent for pattern in patterns for p in root.glob(pattern)}
    return sorted(p for p in found if not p.name.startswith(".") and (not with_key or (p / KEY_NAME).exists()))


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
