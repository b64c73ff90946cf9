"""Ctrl-C stops a run within moments at any point, says which directory to resume, exits 130,
and `ppprops resume` then finishes the run with every candidate recorded once.

Each test starts a real `ppprops run` process in its own process group (as a terminal runs it),
waits for the phase it wants by watching the store or the progress on stderr (never a fixed
sleep), sends SIGINT to the whole group (a terminal's Ctrl-C) and measures the time to exit.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.llm.embedded import MODEL_ALIAS, EmbeddedServer
from ppprops.store import open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer

from interrupting import EXIT_WITHIN_S, Launched, count


def _interrupted(run: Launched, out: Path) -> None:
    """Exit code 130 within the bound, one line naming the real directory, nothing left running."""
    code, elapsed = run.ctrl_c()
    err = run.stderr
    assert code == 130, err[-2000:]
    assert elapsed < EXIT_WITHIN_S, f"took {elapsed:.1f} s to stop"
    assert err.strip().splitlines()[-1] == f"ppprops: interrupted; continue with 'ppprops resume {out}'"
    assert "Traceback" not in err
    assert run.group_gone(), "a child process (embedded server, episode worker) outlived the run"
    store = open_store(out)
    try:
        assert store.status() == "interrupted" and store.final_eval() is None
    finally:
        store.close()


def _resumed(out: Path, total: int, capsys, *extra: str) -> None:  # type: ignore[no-untyped-def]
    before = open_store(out)
    recorded = [(c.index, c.params.tolist()) for c in before.candidates()]
    before.close()
    assert main(["resume", str(out), "--quiet", *extra]) == 0
    capsys.readouterr()
    store = open_store(out)
    try:
        done = store.candidates()
        assert [c.index for c in done] == list(range(total))  # every candidate exactly once
        assert [(c.index, c.params.tolist()) for c in done[: len(recorded)]] == recorded  # nothing redone
        assert store.status() == "finished" and store.final_eval() is not None
    finally:
        store.close()
    assert (out / "best_policy.json").exists()


def test_ctrl_c_during_the_warmup(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    run = Launched(["run", "--env", "Highway-Fast", "--method", "random", "--warmup", "6", "--iterations", "2",
                    "--final-episodes", "2", "--select-top", "0", "--out", str(out), "--quiet"])  # fmt: skip
    run.wait_for(lambda: count(out / "run.sqlite") >= 1, "a warm-up candidate")
    _interrupted(run, out)
    assert 1 <= count(out / "run.sqlite") < 6, "the signal did not land in the warm-up"
    _resumed(out, 8, capsys)


def test_ctrl_c_during_the_final_evaluation(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    run = Launched(["run", "--env", "Highway-Fast", "--method", "random", "--warmup", "2", "--iterations", "0",
                    "--final-episodes", "6", "--select-top", "0", "--out", str(out)])  # fmt: skip
    run.wait_for(lambda: "final evaluation" in run.stderr, "the final evaluation's progress")
    _interrupted(run, out)
    assert count(out / "run.sqlite") == 2
    _resumed(out, 2, capsys)
    store = open_store(out)
    assert len(store.final_eval().returns) == 6  # type: ignore[union-attr]
    store.close()


@pytest.mark.parametrize("answered", [0, 2], ids=["first-call", "later-call"])
def test_ctrl_c_during_a_remote_llm_call(tmp_path: Path, capsys, answered: int) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=answered)) as stalling:  # answers `answered`, then holds
        run = Launched(["run", "--env", "CartPole", "--method", "pp", "--warmup", "3", "--iterations", "4", "--final-episodes", "2", "--select-top", "0",
                        "--base-url", stalling.base_url, "--model", "m", "--retries", "0", "--out", str(out), "--quiet"])  # fmt: skip
        run.wait_for(lambda: stalling.stats()["requests"] > answered, f"LLM request {answered + 1} to arrive")
        _interrupted(run, out)
    assert count(out / "run.sqlite") == 3 + answered
    with FaultServer(FaultConfig(fault_rate=0.0)) as healthy:  # the stalled endpoint is gone: continue elsewhere
        _resumed(out, 7, capsys, "--base-url", healthy.base_url, "--model", "m")


@pytest.mark.llm
@pytest.mark.parametrize("moment", ["model-loading", "first-call", "later-call"])
def test_ctrl_c_with_the_embedded_model(tmp_path: Path, capsys, moment: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    run = Launched(["run", "--env", "CartPole", "--method", "pp", "--warmup", "3", "--iterations", "2", "--final-episodes", "2", "--select-top", "0",
                    "--out", str(out)])  # fmt: skip
    if moment == "model-loading":
        run.wait_for(lambda: "loading the embedded model" in run.stderr, "the model loading")
    elif moment == "first-call":
        run.wait_for(lambda: "embedded model ready" in run.stderr, "the model to be ready")
    else:
        run.wait_for(lambda: count(out / "run.sqlite", "llm_calls") >= 1, "a first recorded LLM call")
    _interrupted(run, out)
    assert count(out / "run.sqlite") < 5
    if moment == "model-loading":
        _resumed(out, 5, capsys)  # with the embedded model again
    else:  # the LLM phase is cheaper against the synthetic endpoint (resume's own test: test_resume_endpoint.py)
        with FaultServer(FaultConfig(fault_rate=0.0)) as healthy:
            _resumed(out, 5, capsys, "--base-url", healthy.base_url, "--model", "m")


# -- the cause: the embedded server can be stopped at any moment ---------------------------------
def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]


def _gone(pid: int, timeout: float = EXIT_WITHIN_S) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not _alive(pid):
            return True
        time.sleep(0.05)
    return False


@pytest.mark.llm
def test_the_embedded_server_stops_at_once_right_after_start_and_mid_request() -> None:
    """The in-process binding hung forever when released right after it started or while a request
    was being processed (its destructor joins a loop thread that never ends); the child process
    stops within moments in both cases."""
    server = EmbeddedServer(context_size=4096).__enter__()
    pid = server.pid
    assert pid is not None and pid != os.getpid() and _alive(pid)
    t0 = time.monotonic()
    server.__exit__(None, None, None)
    assert time.monotonic() - t0 < EXIT_WITHIN_S and _gone(pid)

    with EmbeddedServer(context_size=4096) as server:
        pid = server.pid
        body = json.dumps({"model": MODEL_ALIAS, "messages": [{"role": "user", "content": "1, 2, 3, " * 600}], "max_tokens": 200})
        request = urllib.request.Request(server.base_url + "/chat/completions", data=body.encode(),
                                         headers={"Content-Type": "application/json"})  # fmt: skip
        worker = threading.Thread(target=_ignore_errors, args=(request,), daemon=True)
        worker.start()
        time.sleep(0.5)  # the long prompt is being read (several seconds of prompt processing)
        t0 = time.monotonic()
    assert time.monotonic() - t0 < EXIT_WITHIN_S and _gone(pid)


def _ignore_errors(request: urllib.request.Request) -> None:
    try:
        urllib.request.urlopen(request, timeout=120).read()
    except OSError:
        pass


@pytest.mark.llm
def test_the_embedded_server_ends_when_its_run_is_killed(tmp_path: Path) -> None:
    code = ("from ppprops.llm.embedded import EmbeddedServer\nimport sys, time\n"
            "s = EmbeddedServer(context_size=2048).__enter__()\nprint(s.pid, flush=True)\ntime.sleep(600)\n")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        pid = int(proc.stdout.readline())
        assert _alive(pid)
    finally:
        proc.kill()  # kill -9: no cleanup runs in the parent
        proc.wait()
    assert _gone(pid), "the server outlived the process that started it"
