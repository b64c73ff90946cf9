"""Runs of a grid in parallel processes on this machine.

Each run gets a fresh interpreter (``python -m ppprops.experiments.execute_local``: nothing of
the caller's ``__main__``, llama.cpp or simulators is inherited, and a script calling the API needs
no ``if __name__ == "__main__"`` guard) that starts its own embedded server when the run uses the
embedded model, with ``PPPROPS_LLM_THREADS`` threads, so threads x jobs stays within the cores.
Workers die with the grid process (Linux parent-death signal), so a killed grid leaves no run
half-owned by an orphan; the per-run lock covers the moments in between. With a remote endpoint,
a Manager-held bounded semaphore caps the LLM requests in flight across all workers.

Protocol: the Manager's authkey (so the gate's proxy may connect), then the pickled job arrive on
stdin; the pickled Outcome leaves on the file descriptor named in argv.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import pickle
import secrets as _os_secrets
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from multiprocessing.connection import wait
from multiprocessing.managers import SyncManager
from typing import Any

from .grid import Job, Outcome, execute_job

PR_SET_PDEATHSIG = 1
AUTHKEY_BYTES = 32


def die_with_parent(parent_pid: int | None = None) -> None:
    """Ask Linux to SIGKILL this process when its parent dies (no-op elsewhere)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):
        return
    if parent_pid is not None and os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def _manager_init() -> None:
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, 65536):
        chunks.append(chunk)
    return b"".join(chunks)


def run_local(
    jobs: Sequence[Job],
    *,
    parallel: int,
    llm_threads: int = 1,
    llm_concurrency: int | None = None,
    on_outcome: Callable[[Outcome], None] = lambda o: None,
) -> list[Outcome]:
    """Execute ``jobs`` with at most ``parallel`` at once; outcomes in completion order."""
    manager: SyncManager | None = None
    gate: Any = None
    authkey = _os_secrets.token_bytes(AUTHKEY_BYTES)
    if llm_concurrency is not None:
        manager = SyncManager(authkey=authkey, ctx=mp.get_context("spawn"))
        manager.start(_manager_init)
        gate = manager.BoundedSemaphore(llm_concurrency)
    queue = list(jobs)
    running: dict[int, tuple[subprocess.Popen[bytes], Job]] = {}  # read end of the result pipe -> worker
    outcomes: list[Outcome] = []
    try:
        while queue or running:
            while queue and len(running) < parallel:
                job = queue.pop(0)
                r, w = os.pipe()
                proc = subprocess.Popen(
                    [sys.executable, "-m", __name__, str(w), str(os.getpid())],
                    stdin=subprocess.PIPE, pass_fds=(w,), start_new_session=False,
                )  # fmt: skip
                os.close(w)
                assert proc.stdin is not None
                proc.stdin.write(authkey + pickle.dumps((job, llm_threads, gate)))
                proc.stdin.close()
                running[r] = (proc, job)
            for ready in wait(list(running)):
                r = int(ready)  # type: ignore[arg-type]  # wait() on plain descriptors hands them back
                proc, job = running.pop(r)
                data = _read_all(r)
                os.close(r)
                proc.wait()
                outcome: Outcome | None = None
                try:
                    outcome = pickle.loads(data) if data else None
                except (pickle.UnpicklingError, EOFError, AttributeError):
                    outcome = None
                if outcome is None:
                    outcome = Outcome(job.name, "failed", "", None, None, 0.0,
                                      error=f"worker died (exit code {proc.returncode}); rerun the grid to continue the run")  # fmt: skip
                outcomes.append(outcome)
                on_outcome(outcome)
    finally:
        for proc, _ in running.values():  # interrupted: stop the workers, the runs stay resumable
            proc.terminate()
        for r, (proc, _) in running.items():
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
            os.close(r)
        if manager is not None:
            manager.shutdown()
    return outcomes


def _worker(argv: list[str]) -> int:
    """One run in this process; the grid process started it."""
    out_fd, parent = int(argv[0]), int(argv[1])
    die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the grid, which stops its workers
    raw = sys.stdin.buffer.read()
    mp.current_process().authkey = raw[:AUTHKEY_BYTES]  # before the gate proxy is rebuilt: it connects on unpickling
    job, llm_threads, gate = pickle.loads(raw[AUTHKEY_BYTES:])
    outcome = execute_job(job, llm_threads=llm_threads, llm_gate=gate)
    with os.fdopen(out_fd, "wb") as f:
        f.write(pickle.dumps(outcome))
    return 0


if __name__ == "__main__":
    sys.exit(_worker(sys.argv[1:]))
