"""A grid directory, its master key, and the execution of one run (shared by every executor).

Layout of ``DIR``::

    master.key      32 random bytes (hex), mode 0600: every run's secrets derive from it
    grid.json       the planned runs (name -> configuration) and each invocation
    runs/<name>/    one ordinary run directory per run (ppprops show / resume / policy eval work on it)
    locks/<name>    held while a process executes that run
    report/         written by ``ppprops report DIR``

Secrets: a run's A and c (and, for hardened runs, its origins and warp exponent) are drawn from
``numpy.random.default_rng(HMAC-SHA256(master key, "ppprops.grid-secrets/1" NUL name))`` with
``client.hardening.generate_secrets``, the routine every run draws its secrets with
(docs/privacy.md). The same key and name therefore give the same secrets on any machine, which is
what makes a grid repeat exactly on Ray or elsewhere; whoever holds ``master.key`` holds every
run's secrets, so it is created 0600 and never leaves ``DIR``.

Resumption: a run whose store says finished (or stopped on purpose) is skipped, one that is
running is continued with ``runner.resume``, a missing one is started. An RL baseline cannot be
resumed, so an unfinished one is trained again from scratch (same seed).
"""

from __future__ import annotations

import fcntl
import hashlib
import hmac
import json
import os
import secrets as _os_secrets
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError, PPPropsError, StoreError
from ..fileio import write_json_atomic
from .spec import RL, ExperimentSpec, PlannedRun

if TYPE_CHECKING:
    from ..client.secrets import Secrets
    from ..config import RunConfig

MASTER_KEY = "master.key"
MANIFEST = "grid.json"
RUNS = "runs"
LOCKS = "locks"
GRID_FORMAT = "ppprops.grid/1"
KEY_FORMAT = "ppprops.grid-key/1"
DERIVE_TAG = b"ppprops.grid-secrets/1\x00"
LOCK_WAIT_S = 30.0  # a killed grid's workers die with it; their locks are free within moments

DONE, PARTIAL, PENDING = "done", "partial", "pending"


# -- master key and derived secrets -------------------------------------------------------------
def create_master_key(path: Path) -> bytes:
    """32 bytes from the OS entropy source, written with mode 0600 from the start; returns the key.

    The file is JSON (``{"format": KEY_FORMAT, "key": <hex>}``). Raises FileExistsError when
    ``path`` exists already: a key is never overwritten.
    """
    key = _os_secrets.token_bytes(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        json.dump({"format": KEY_FORMAT, "key": key.hex()}, f)
        f.flush()
        os.fsync(f.fileno())
    return key


def read_master_key(path: Path) -> bytes:
    """The key bytes of a master key file written by ``create_master_key``.

    Raises:
        ConfigError: the file is missing, is not a ``ppprops.grid-key/1`` document, or holds a key
            shorter than 16 bytes.
    """
    try:
        raw = json.loads(Path(path).read_text(encoding="utf-8"))
        if raw.get("format") != KEY_FORMAT:
            raise ValueError("format")
        key = bytes.fromhex(raw["key"])
    except FileNotFoundError:
        raise ConfigError(f"master key {path} is missing") from None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        raise ConfigError(f"master key {path} is corrupt") from None
    if len(key) < 16:
        raise ConfigError(f"master key {path} is too short")
    return key


def derived_rng(master_key: bytes, name: str) -> np.random.Generator:
    """numpy's default generator seeded with HMAC-SHA256(master_key, DERIVE_TAG + name) (a 256-bit seed).

    Deterministic: the same key and run name give the same stream on every machine.
    """
    digest = hmac.new(master_key, DERIVE_TAG + name.encode("utf-8"), hashlib.sha256).digest()
    return np.random.default_rng(int.from_bytes(digest, "big"))


def derive_secrets(master_key: bytes, name: str, config: RunConfig) -> Secrets:
    """The run's secrets, drawn by ``client.hardening.generate_secrets`` (the one routine runs use
    too) from a generator keyed by the master key and the run's name instead of the OS.

    Raises:
        ConfigError, UnknownTaskError: the run's task cannot be built here (``RunConfig.make_task``).
    """
    from ..client.hardening import generate_secrets

    return generate_secrets(name, config.make_task(), config.encoding, rng=derived_rng(master_key, name))


# -- run state and locks ---------------------------------------------------------------------
def run_state(run_dir: Path, kind: str) -> str:
    """done (finished, or stopped on purpose), partial (resumable), or pending (nothing usable)."""
    from ..status import RunKind, is_complete
    from ..store import DB_NAME, open_store

    if not (Path(run_dir) / DB_NAME).exists():
        return PENDING
    try:
        with open_store(run_dir) as store:
            status = store.status()
    except StoreError:
        return PENDING
    if is_complete(status, RunKind(kind)):
        return DONE
    return PARTIAL if kind != RL else PENDING  # an RL baseline cannot be continued: trained again


@contextmanager
def run_lock(path: Path, wait_s: float = LOCK_WAIT_S) -> Iterator[None]:
    """An exclusive flock, so two grid processes never execute one run at the same time."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise StoreError(f"run {Path(path).name} is being executed by another process (lock {path})") from None
                time.sleep(0.2)
        yield
    finally:
        os.close(fd)  # releases the lock


# -- one run ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Job:
    """Everything a worker needs for one run; picklable (sent to processes and Ray tasks)."""

    name: str
    kind: str
    config: dict[str, Any]
    run_dir: str
    lock: str
    secrets: Any = None  # Secrets for a search run; None for an RL baseline


@dataclass(frozen=True)
class Outcome:
    """How the execution of one run ended, as a worker reports it to the grid.

    ``action``: what was done (started, resumed, skipped, or failed with ``error`` holding the
    one-line reason). ``best`` is the search-time best finite candidate return, ``final`` the mean
    final-evaluation return (both raw reward units; None when there is none). ``wall_s``: seconds
    the worker spent on it, waiting for its lock included.
    """

    name: str
    action: str  # started | resumed | skipped | failed
    status: str  # the store's status afterwards ("" if none)
    best: float | None  # search-time best return (None for RL)
    final: float | None  # final-evaluation mean
    wall_s: float
    error: str | None = None


def _same_config(stored: dict[str, Any], planned: dict[str, Any]) -> bool:
    """A stored config matches when every planned key has the planned value (RL stores extra keys).

    A search config is first read back through ``RunConfig.from_json``, so one written before a
    setting existed (e.g. ``describe_task``) compares with that setting's default."""
    from ..config import RunConfig
    from ..status import RunKind

    if RunKind.of_config(stored) is RunKind.SEARCH:
        try:
            stored = RunConfig.from_json(stored).to_json()
        except (KeyError, TypeError, ValueError):
            pass  # not a config this version reads: compare as it is
    norm = json.loads(json.dumps(planned))
    stored = json.loads(json.dumps(stored))
    return all(stored.get(k) == v for k, v in norm.items())


def _summary(run_dir: Path) -> tuple[str, float | None, float | None]:
    from ..store import open_store

    with open_store(run_dir) as store:
        status = store.status()
        fe = store.final_eval()
        cands = store.candidates()
    finite = [c.ret for c in cands if np.isfinite(c.ret)]
    return status, (max(finite) if finite else None), (fe.mean if fe is not None and fe.returns else None)


def execute_job(job: Job, *, llm_threads: int = 1, llm_gate: Any = None) -> Outcome:
    """Start, resume or skip one run, in this process. Failures come back as an Outcome."""
    t0 = time.monotonic()
    os.environ["PPPROPS_LLM_THREADS"] = str(llm_threads)  # read by the embedded server this run starts
    run_dir = Path(job.run_dir)
    try:
        with run_lock(Path(job.lock)):
            state = run_state(run_dir, job.kind)
            if state != PENDING:
                from ..store import open_store

                with open_store(run_dir) as store:
                    stored = store.config()
                if not _same_config(stored, job.config):
                    raise ConfigError(f"{run_dir} holds run {job.name} with other settings than this grid's; "
                                      "use a new --out or the spec it was started with")  # fmt: skip
            if state == DONE:
                status, best, final = _summary(run_dir)
                return Outcome(job.name, "skipped", status, best, final, time.monotonic() - t0)
            if job.kind == RL:
                from ..baselines.rl import RLConfig, run_baseline

                if run_dir.exists():
                    shutil.rmtree(run_dir)  # an unfinished RL run cannot continue: train again, same seed
                run_baseline(RLConfig(**job.config), run_dir)
                action = "started"
            else:
                from .. import runner
                from ..config import RunConfig

                gate = {"llm_gate": llm_gate} if llm_gate is not None else {}
                if state == PARTIAL:
                    runner.resume(run_dir, **gate)
                    action = "resumed"
                else:
                    if run_dir.exists() and not any(run_dir.iterdir()):
                        run_dir.rmdir()
                    runner.start(RunConfig.from_json(job.config), run_dir, secrets=job.secrets, **gate)
                    action = "started"
            status, best, final = _summary(run_dir)
            return Outcome(job.name, action, status, best, final, time.monotonic() - t0)
    except PPPropsError as e:
        return Outcome(job.name, "failed", "", None, None, time.monotonic() - t0, error=str(e))
    except Exception as e:  # a worker must report, never vanish
        return Outcome(job.name, "failed", "", None, None, time.monotonic() - t0, error=f"{e.__class__.__name__}: {e}")


# -- the grid directory ----------------------------------------------------------------------
def manifest_problem(doc: Any) -> str:
    """What makes ``doc`` (a parsed ``grid.json``) unusable, or "" when it is a grid manifest.

    A manifest is an object of format ``GRID_FORMAT`` with a ``grid_id`` string, an ``invocations``
    list and a ``runs`` object whose entries each hold ``kind``, ``task``, ``method`` (strings), an
    integer ``seed`` and a ``config`` object.
    """
    if not isinstance(doc, dict):
        return "not a JSON object"
    if doc.get("format") != GRID_FORMAT:
        return f"format is not {GRID_FORMAT}"
    if not isinstance(doc.get("grid_id"), str) or not isinstance(doc.get("invocations"), list) or not isinstance(doc.get("runs"), dict):
        return "grid_id, invocations or runs missing or of the wrong type"
    for name, entry in doc["runs"].items():
        if not (isinstance(entry, dict) and all(isinstance(entry.get(k), str) for k in ("kind", "task", "method"))
                and isinstance(entry.get("seed"), int) and isinstance(entry.get("config"), dict)):  # fmt: skip
            return f"run entry {name!r} is not an object with kind, task, method, seed and config"
    return ""


class Grid:
    """A grid directory: opens (or creates) it, checks the spec against it, and makes jobs."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.runs_dir = self.root / RUNS
        self.locks_dir = self.root / LOCKS

    @classmethod
    def open(cls, root: Path, spec: ExperimentSpec) -> Grid:
        """Open the grid directory ``root`` for ``spec``, creating it (and its master key) if needed.

        Adds the spec's runs to ``grid.json`` and this invocation to its list, and removes run
        directories left half-created by a killed run. An empty directory, or one holding only a
        copied ``master.key`` (to repeat that grid's secrets), becomes a new grid.

        Raises:
            ConfigError: ``root`` is a file, holds files but no ``grid.json``, its ``grid.json`` is
                corrupt, or a run of ``spec`` is already planned there with other settings.
        """
        grid = cls(root)
        if grid.root.exists() and not grid.root.is_dir():
            raise ConfigError(f"--out {root} is a file, not a directory")
        manifest_path = grid.root / MANIFEST
        foreign = grid.root.exists() and any(p.name != MASTER_KEY for p in grid.root.iterdir())
        if foreign and not manifest_path.exists():  # a copied master.key alone is welcome: it repeats that grid
            raise ConfigError(f"--out {root} holds files but no {MANIFEST}: it is not a grid directory; choose a new --out")
        grid.runs_dir.mkdir(parents=True, exist_ok=True)
        grid.locks_dir.mkdir(parents=True, exist_ok=True)
        manifest: dict[str, Any] = {"format": GRID_FORMAT, "grid_id": _os_secrets.token_hex(8), "runs": {}, "invocations": []}
        if manifest_path.exists():
            try:
                stored: Any = json.loads(manifest_path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                stored = None
            problem = manifest_problem(stored)
            if problem:
                raise ConfigError(f"{manifest_path} is corrupt ({problem}); it is not a grid this ppprops can continue")
            manifest = stored
        for run in spec.runs:
            known = manifest["runs"].get(run.name)
            if known is not None and not _same_config(known["config"], run.config):
                changed = sorted(k for k, v in json.loads(json.dumps(run.config)).items() if known["config"].get(k) != v)
                raise ConfigError(f"run {run.name} already exists in {root} with other settings ({', '.join(changed)}); "
                                  "rerun with the spec and flags it was started with, or use a new --out")  # fmt: skip
            manifest["runs"][run.name] = {"kind": run.kind, "task": run.task, "method": run.method, "label": run.label,
                                          "seed": run.seed, "config": run.config}  # fmt: skip
        manifest["invocations"].append({"time": time.strftime("%Y-%m-%dT%H:%M:%S"), "spec": spec.name, "source": spec.source,
                                        "runs": [r.name for r in spec.runs]})  # fmt: skip
        if not (grid.root / MASTER_KEY).exists():
            create_master_key(grid.root / MASTER_KEY)
        write_json_atomic(manifest_path, manifest, indent=1, sort_keys=True)
        for stale in grid.runs_dir.glob(".*.creating"):  # left by a run killed while its directory was being made
            shutil.rmtree(stale, ignore_errors=True)
        return grid

    @property
    def grid_id(self) -> str:
        """The random id (16 hex digits) written when the grid was created; Ray tasks use it to
        tell whether they see this grid's directory."""
        return str(self.manifest()["grid_id"])

    def manifest(self) -> dict[str, Any]:
        """``grid.json`` as read now (format, grid_id, runs, invocations).

        Raises OSError or ValueError when the file is missing or not JSON (``open`` checks it).
        """
        return dict(json.loads((self.root / MANIFEST).read_text(encoding="utf-8")))

    def record(self, **entry: Any) -> None:
        """Add executor details to the latest invocation (jobs, threads, where it ran)."""
        m = self.manifest()
        m["invocations"][-1].update(entry)
        write_json_atomic(self.root / MANIFEST, m, indent=1, sort_keys=True)

    def run_dir(self, name: str) -> Path:
        """``runs/<name>`` under the grid root (it may not exist yet)."""
        return self.runs_dir / name

    def state(self, run: PlannedRun) -> str:
        """``DONE``, ``PARTIAL`` or ``PENDING`` for ``run`` (see ``run_state``)."""
        return run_state(self.run_dir(run.name), run.kind)

    def job(self, run: PlannedRun) -> Job:
        """The Job that executes ``run``: its config, directory, lock and, for a search, its secrets
        derived from the master key (``derive_secrets``).

        Raises:
            ConfigError: the master key is missing or corrupt, or the run's task cannot be built.
        """
        secrets = None
        if run.kind != RL:
            from ..config import RunConfig

            key = read_master_key(self.root / MASTER_KEY)
            secrets = derive_secrets(key, run.name, RunConfig.from_json(run.config))
        return Job(run.name, run.kind, run.config, str(self.run_dir(run.name)), str(self.locks_dir / run.name), secrets)
