"""Advisory file locks in a run directory (POSIX ``flock``): they die with the process that holds them.

Two locks: ``STUDY_LOCK`` serialises a study's ``ask`` and ``tell`` across processes (a second
``ask`` while one is asking the LLM waits, then gets the same pending trial), and ``RUNNING_LOCK``
is held for as long as a process runs the search (``Study.optimize``), so ``status.effective``
can tell a running run from one whose process is gone (``kill -9``, a crash).
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import StoreError

STUDY_LOCK = ".study.lock"
RUNNING_LOCK = ".running.lock"


@contextmanager
def file_lock(run_dir: str | os.PathLike[str], name: str, *, wait: bool = True) -> Iterator[None]:
    """Hold the lock ``name`` in ``run_dir`` for the block. ``wait=False``: raise BlockingIOError
    at once when another process holds it. StoreError when the lock file cannot be opened."""
    path = Path(run_dir) / name
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError as e:
        raise StoreError(f"cannot open the lock file {path}: {e.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def held(run_dir: str | os.PathLike[str], name: str) -> bool:
    """True when a process (this one included, through another open) holds the lock ``name`` in ``run_dir``."""
    path = Path(run_dir) / name
    if not path.exists():
        return False
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)
