"""Helpers for Ctrl-C tests: a `ppprops` subprocess in its own process group (as a terminal runs
it), its stderr read as it comes. (An LLM endpoint that answers a few requests and then stalls, so
a test can signal while a later request is in flight, is the fault server's ``hold_after``.)"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

EXIT_WITHIN_S = 10.0  # generous: a loaded 2-core machine; the run itself needs well under a second
PHASE_WAIT_S = 300.0  # how long a test waits for the phase it wants to interrupt


def count(db: Path, table: str = "candidates") -> int:
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5) as con:
            return int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
    except sqlite3.Error:
        return 0


class Launched:
    """``python -m ppprops ARGS`` in a new session (its own process group, like a terminal job)."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None) -> None:
        # a terminal job gets Ctrl-C; a suite started in the background by a non-interactive shell ignores SIGINT,
        # and a child would inherit that: restore the default, as a terminal would
        self.proc = subprocess.Popen([sys.executable, "-m", "ppprops", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     start_new_session=True, env=env,
                                     preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
        self._err: list[bytes] = []
        self._out: list[bytes] = []
        self._threads = [threading.Thread(target=self._pump, args=(self.proc.stderr, self._err), daemon=True),
                         threading.Thread(target=self._pump, args=(self.proc.stdout, self._out), daemon=True)]  # fmt: skip
        for t in self._threads:
            t.start()

    @staticmethod
    def _pump(stream, sink: list[bytes]) -> None:  # type: ignore[no-untyped-def]
        fd = stream.fileno()
        while chunk := os.read(fd, 65536):
            sink.append(chunk)

    @property
    def stderr(self) -> str:
        return b"".join(self._err).decode("utf-8", "replace")

    @property
    def stdout(self) -> str:
        return b"".join(self._out).decode("utf-8", "replace")

    def wait_for(self, condition: Callable[[], bool], what: str, timeout: float = PHASE_WAIT_S) -> None:
        """Poll until ``condition()``; fails if the process ends first or the time runs out."""
        deadline = time.monotonic() + timeout
        while not condition():
            if self.proc.poll() is not None:
                raise AssertionError(f"the run ended (code {self.proc.returncode}) before {what}:\n{self.stderr[-2000:]}")
            if time.monotonic() > deadline:
                self.kill()
                raise AssertionError(f"no {what} within {timeout:.0f} s:\n{self.stderr[-2000:]}")
            time.sleep(0.02)

    def ctrl_c(self) -> tuple[int, float]:
        """SIGINT to the whole process group, as a terminal's Ctrl-C; returns (exit code, seconds to exit)."""
        t0 = time.monotonic()
        os.killpg(self.proc.pid, signal.SIGINT)
        try:
            code = self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"still running 60 s after Ctrl-C:\n{self.stderr[-2000:]}") from None
        elapsed = time.monotonic() - t0
        for t in self._threads:
            t.join(timeout=5)
        return code, elapsed

    def group_gone(self, timeout: float = EXIT_WITHIN_S) -> bool:
        """No process of the group is left (the embedded server and episode workers ended too)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                os.killpg(self.proc.pid, 0)
            except ProcessLookupError:
                return True
            time.sleep(0.05)
        return False

    def kill(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait()
