"""A study driven from the shell keeps the embedded model warm (llm.embedded.WarmServer).

Each ``ppprops ask`` is a new process; the first that needs the model starts a server detached
from it and records it in the study's ``.llm-server.json``, the next ones connect to it. It stops
when the study is finalized, after ``PPPROPS_LLM_IDLE_S`` seconds without a request, and a record
whose server is gone (or whose pid now runs another program) gets a fresh one. Every request still
goes through the ask process's recording client, so the audit reads the study as before.

The tests marked ``llm`` load the real model (a few seconds per start); a fixture kills any warm
server a test leaves behind.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from ppprops.errors import ConfigError
from ppprops.llm.embedded import IDLE_ENV, LOCK_NAME, STATE_NAME, idle_seconds, stop_warm_server, warm_server_state
from ppprops.store import open_store

ROOT = Path(__file__).resolve().parents[1]
SRC = str(ROOT / "src")


def _ppprops(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    full = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", ""), **env}
    return subprocess.run([sys.executable, "-m", "ppprops", *args], cwd=cwd, capture_output=True, text=True, env=full, timeout=300)


def _servers(study: Path) -> list[int]:
    """Live warm servers of ``study`` (zombies have no command line, so they do not count)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            args = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"ppprops.llm.embedded" in args and b"--warm" in args and str(study.resolve()).encode() in args:
            found.append(int(entry.name))
    return found


def _gone(pid: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if not Path(f"/proc/{pid}/cmdline").read_bytes():
                return True  # a zombie
        except OSError:
            return True
        time.sleep(0.1)
    return False


@pytest.fixture
def study(tmp_path: Path) -> Iterator[Path]:
    """A pp-hardened CartPole study (1 warm-up trial, 3 LLM trials); no warm server of it outlives the test."""
    made = _ppprops(["study", "create", "--env", "CartPole", "--method", "pp-hardened", "--warmup", "1", "--iterations", "3",
                     "--select-top", "0", "--final-episodes", "1", "--seed", "3", "--out", "st"], tmp_path)  # fmt: skip
    assert made.returncode == 0, made.stderr
    yield tmp_path / "st"
    for pid in _servers(tmp_path / "st"):
        os.kill(pid, signal.SIGKILL)


def _ask(study: Path, **env: str) -> dict:
    asked = _ppprops(["ask", study.name], study.parent, **env)
    assert asked.returncode == 0, asked.stderr
    return json.loads(asked.stdout)


def _tell(study: Path, trial: dict, ret: float) -> None:
    told = _ppprops(["tell", study.name, str(trial["trial"]), "--return", str(ret)], study.parent)
    assert told.returncode == 0, told.stderr


@pytest.mark.llm
def test_llm_asks_share_one_warm_server_that_finalize_stops(study: Path) -> None:
    _tell(study, _ask(study), 10.0)
    assert warm_server_state(study) is None and not _servers(study)  # a warm-up trial needs no model
    # two asks at once for the first LLM trial: one server, one trial
    full = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    both = [subprocess.Popen([sys.executable, "-m", "ppprops", "ask", "st"], cwd=study.parent, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=full) for _ in range(2)]  # fmt: skip
    outs = [p.communicate(timeout=300) for p in both]
    assert [p.returncode for p in both] == [0, 0], [o[1] for o in outs]
    first, again = (json.loads(o[0]) for o in outs)
    assert first == again and first["source"] == "llm"
    state = warm_server_state(study)
    assert state is not None and [s["pid"] for s in state["starts"]] == [state["pid"]]
    pid = state["pid"]
    assert _servers(study) == [pid]
    # detached: not in this session or process group (Ctrl-C at the terminal never reaches it)
    assert os.getsid(pid) != os.getsid(0) and os.getpgid(pid) != os.getpgid(0)
    _tell(study, first, 12.0)
    second = _ask(study)
    assert second["source"] == "llm" and second["trial"] == 2
    state = warm_server_state(study)
    assert state is not None and state["pid"] == pid and len(state["starts"]) == 1  # the second LLM ask started nothing
    assert _servers(study) == [pid]
    _tell(study, second, 14.0)
    with open_store(study) as store:
        assert store.llm_sessions() is not None and len(store.llm_sessions() or []) == 2  # one client session per ask process
    done = _ppprops(["study", "finalize", "st"], study.parent)  # before the budget: the server is still up
    assert done.returncode == 0, done.stderr
    assert _gone(pid) and not _servers(study) and not (study / STATE_NAME).exists()
    # every request of the asks recorded and read; nothing raw, nothing unaccounted for (the verdict itself
    # is the model's: a proposal at the box's edge in two answers lets clip-edge read one a_j now and then)
    audit = _ppprops(["audit", "st", "--json"], study.parent)
    doc = json.loads(audit.stdout)
    with open_store(study) as store:
        sent = len(store.llm_calls())
    assert sent >= 2 and doc["requests"] == sent and doc["unanswered"] == [], audit.stdout  # 2 LLM trials, and any retries
    assert not {f["severity"] for f in doc["findings"]} & {"leak", "unverified", "identifier"}, audit.stdout
    assert audit.returncode == (0 if doc["verdict"].startswith("CLEAN") else 1), audit.stdout


@pytest.mark.llm
def test_an_idle_warm_server_stops_by_itself(study: Path) -> None:
    _tell(study, _ask(study), 10.0)
    _ask(study, **{IDLE_ENV: "3"})
    state = warm_server_state(study)
    assert state is not None and state["idle_s"] == 3.0
    assert _gone(state["pid"], timeout=30.0), "the idle server did not stop"
    assert not (study / STATE_NAME).exists() and not _servers(study)


@pytest.mark.llm
def test_a_stale_record_gets_a_fresh_server_and_a_reused_pid_is_left_alone(study: Path) -> None:
    _tell(study, _ask(study), 10.0)
    trial = _ask(study)
    state = warm_server_state(study)
    assert state is not None
    os.kill(state["pid"], signal.SIGKILL)
    assert _gone(state["pid"])
    _tell(study, trial, 12.0)
    # the dead server's pid now runs another program
    other = subprocess.Popen(["sleep", "120"])
    try:
        stale = {**state, "pid": other.pid}
        (study / STATE_NAME).write_text(json.dumps(stale))
        second = _ask(study)
        assert second["source"] == "llm" and second["trial"] == 2
        fresh = warm_server_state(study)
        assert fresh is not None and fresh["pid"] not in (state["pid"], other.pid) and fresh["token"] != state["token"]
        assert [s["pid"] for s in fresh["starts"]] == [state["pid"], fresh["pid"]]
        assert _servers(study) == [fresh["pid"]] and other.poll() is None  # the other program was not touched
    finally:
        other.kill()
        other.wait()


# -- without the model ---------------------------------------------------------------------------
def test_the_idle_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(IDLE_ENV, raising=False)
    assert idle_seconds() == 600.0
    for text, value in (("3", 3.0), ("0", 0.0), (" 2.5 ", 2.5)):
        monkeypatch.setenv(IDLE_ENV, text)
        assert idle_seconds() == value
    for bad in ("-1", "soon", "inf", "nan"):
        monkeypatch.setenv(IDLE_ENV, bad)
        with pytest.raises(ConfigError, match=f"{IDLE_ENV} must be a number of seconds >= 0"):
            idle_seconds()


def test_stopping_touches_nothing_but_a_warm_server(tmp_path: Path) -> None:
    assert stop_warm_server(tmp_path) is False
    assert list(tmp_path.iterdir()) == []  # a run that never had a warm server gets no files
    other = subprocess.Popen(["sleep", "120"])  # a record whose pid runs another program
    try:
        (tmp_path / STATE_NAME).write_text(json.dumps({"pid": other.pid, "token": "abc", "url": "http://127.0.0.1:1"}))
        assert stop_warm_server(tmp_path) is False
        assert other.poll() is None and not (tmp_path / STATE_NAME).exists() and (tmp_path / LOCK_NAME).exists()
    finally:
        other.kill()
        other.wait()
