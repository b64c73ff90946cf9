"""Runs of a grid as Ray tasks: ``--ray-address ADDRESS`` joins a cluster, ``--ray local`` starts one here.

Each run is one task asking for ``llm_threads`` CPUs, so Ray packs as many runs per node as its
cores allow, each with its own embedded server of that many threads; the same job executed by
the same code gives the same numbers as a local grid. A remote endpoint is shared through an
actor-held semaphore (``RayGate``) that caps the LLM requests in flight across the cluster.

Where a task finds the grid directory (the same path with the same grid id, as on this machine
or a shared file system) it works there in place, resumable at any point. Elsewhere it receives
the run directory as it stands (nothing, or an interrupted run), works in a scratch directory,
and sends the result back, which the driver puts in place; an interrupted remote run then
continues from where the driver last saw it. Every node needs ppprops (and the extras the runs
use) installed, and the Ray versions must match.
"""

from __future__ import annotations

import io
import os
import shutil
import tarfile
import tempfile
import uuid
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..errors import ConfigError
from ..ray_cluster import connect, import_ray
from .grid import MANIFEST, Job, Outcome, execute_job

TRANSFER = ("auto", "ship")


def _ray() -> Any:
    return import_ray("ppprops experiment --ray / --ray-address")


class RayGate:
    """A context manager around an actor's semaphore: ``with gate:`` holds one of N permits."""

    def __init__(self, actor: Any) -> None:
        self.actor = actor

    def __enter__(self) -> RayGate:
        _ray().get(self.actor.acquire.remote())
        return self

    def __exit__(self, *exc: object) -> None:
        _ray().get(self.actor.release.remote())


class _Semaphore:
    """The actor behind RayGate (async, so waiting acquirers do not block releases)."""

    def __init__(self, permits: int) -> None:
        import asyncio

        self._sem = asyncio.Semaphore(permits)

    async def acquire(self) -> None:
        await self._sem.acquire()

    async def release(self) -> None:
        self._sem.release()


def make_gate(permits: int) -> RayGate:
    """A RayGate over a new semaphore actor (0 CPUs) with ``permits`` permits (>= 1), on the connected Ray instance.

    Raises:
        MissingExtraError: Ray (the ``ray`` extra) is not installed.
    """
    ray = _ray()
    actor = ray.remote(num_cpus=0)(_Semaphore).remote(permits)
    return RayGate(actor)


def pack_dir(path: Path) -> bytes | None:
    """A run directory as tar bytes (None when there is none)."""
    path = Path(path)
    if not path.is_dir():
        return None
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        tar.add(path, arcname=".")
    return buf.getvalue()


def unpack_dir(data: bytes, dest: Path) -> None:
    """Extract ``pack_dir``'s gzip tar bytes into ``dest`` (created if missing).

    Uses tarfile's ``data`` filter: members that would land outside ``dest``, links pointing out of
    it and special files raise ``tarfile.FilterError`` instead of being written.
    """
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        tar.extractall(dest, filter="data")


def _sees_grid(job: Job, grid_id: str) -> bool:
    import json

    try:
        doc = json.loads((Path(job.run_dir).parent.parent / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return bool(doc.get("grid_id") == grid_id)


def ray_task(job: Job, grid_id: str, transfer: str, packed: bytes | None, llm_threads: int, gate: Any) -> tuple[Outcome, bytes | None]:
    """Body of one Ray task: in place when the grid directory is visible, else in scratch."""
    if transfer == "auto" and _sees_grid(job, grid_id):
        return execute_job(job, llm_threads=llm_threads, llm_gate=gate), None
    scratch = Path(tempfile.mkdtemp(prefix="ppprops-ray-"))
    try:
        run_dir = scratch / "runs" / Path(job.run_dir).name
        if packed is not None:
            unpack_dir(packed, run_dir)
        local = replace(job, run_dir=str(run_dir), lock=str(scratch / "lock"))
        outcome = execute_job(local, llm_threads=llm_threads, llm_gate=gate)
        return outcome, (pack_dir(run_dir) if outcome.action in ("started", "resumed") or run_dir.exists() else None)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _put_back(job: Job, data: bytes) -> None:
    """Replace the driver's copy of a run with the one a remote task finished."""
    target = Path(job.run_dir)
    incoming = target.parent / f".{target.name}.{uuid.uuid4().hex[:8]}.incoming"
    unpack_dir(data, incoming)
    if target.exists():
        old = target.parent / f".{target.name}.{uuid.uuid4().hex[:8]}.old"
        os.rename(target, old)
        os.rename(incoming, target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(incoming, target)


def run_ray(
    jobs: Sequence[Job],
    *,
    address: str,
    grid_id: str,
    llm_threads: int = 1,
    llm_concurrency: int | None = None,
    transfer: str = "auto",
    on_outcome: Callable[[Outcome], None] = lambda o: None,
) -> list[Outcome]:
    """Execute ``jobs`` on Ray (``address`` "local" starts a private instance on this machine).

    Each job is one Ray task of ``llm_threads`` CPUs (retried twice if its worker dies); at most
    ``llm_concurrency`` LLM requests are in flight across all of them (None: no cap). With
    ``transfer`` "auto" a task works in place when it sees the grid ``grid_id`` at the same path,
    else (and always with "ship") on a copy of the run directory that comes back to the driver.
    ``on_outcome`` is called in the driver as each run ends. A Ray instance this call started is
    shut down at the end; one already connected is left as it is.

    Returns:
        One Outcome per job, in the order they ended; a task lost to Ray is an Outcome "failed".

    Raises:
        ConfigError: an unknown ``transfer``, or the cluster at ``address`` cannot be reached.
        MissingExtraError: Ray (the ``ray`` extra) is not installed.
    """
    if transfer not in TRANSFER:
        raise ConfigError(f"transfer must be one of {', '.join(TRANSFER)}, got {transfer!r}")
    ray, started = connect(address, "--ray-address" if address != "local" else "--ray")
    try:
        gate = make_gate(llm_concurrency) if llm_concurrency is not None else None
        remote = ray.remote(ray_task).options(num_cpus=llm_threads, max_retries=2, retry_exceptions=False)
        pending = {}
        for job in jobs:
            packed = pack_dir(Path(job.run_dir)) if transfer == "ship" or Path(job.run_dir).exists() else None
            pending[remote.remote(job, grid_id, transfer, packed, llm_threads, gate)] = job
        outcomes: list[Outcome] = []
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(ready[0])
            try:
                outcome, data = ray.get(ready[0])
                if data is not None:
                    _put_back(job, data)
            except Exception as e:  # a task lost with its node: the run stays as it was here
                outcome = Outcome(job.name, "failed", "", None, None, 0.0, error=f"Ray task failed: {e.__class__.__name__}: {e}")
            outcomes.append(outcome)
            on_outcome(outcome)
        return outcomes
    finally:
        if started:
            ray.shutdown()
