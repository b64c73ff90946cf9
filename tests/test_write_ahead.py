"""A request the endpoint received is a request the store holds, even when the process that sent it
is killed (SIGKILL: no handler runs) while the request is in flight: every try is written to the
store before its bytes leave (``llm.recording``), left unanswered by a killed process, read by
``ppprops audit`` like any other and counted by ``ppprops show``.

The endpoint is the fault server holding the requests after the first few open (``hold_after``)
and keeping every request it received byte for byte (``record``). The study is driven from Python
(``create_study``, one process), from the shell (``ppprops ask``), and from P threads sending at once.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from ppprops.errors import StoreError
from ppprops.llm.client import EndpointClient
from ppprops.llm.recording import RecordingLLM
from ppprops.llm.settings import LLMConfig
from ppprops.privacy.audit import audit_run
from ppprops.store import RunStore, open_store
from ppprops.summary import format_summary, run_summary
from ppprops.testing.fault_server import FaultConfig, FaultServer

from support import chat_request

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
WAIT_S = 120.0


def _launch(args: list[str], cwd: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(args, cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)


def _kill_once(proc: subprocess.Popen[bytes], server: FaultServer, arrived: int) -> None:
    """SIGKILL ``proc``'s process group once ``arrived`` requests reached the server (the last held open)."""
    deadline = time.monotonic() + WAIT_S
    while server.stats()["requests"] < arrived:
        if proc.poll() is not None:
            raise AssertionError(f"ended (code {proc.returncode}) before request {arrived} arrived: {proc.stderr.read().decode()[-2000:]}")  # type: ignore[union-attr]
        assert time.monotonic() < deadline, f"request {arrived} did not arrive within {WAIT_S:.0f} s"
        time.sleep(0.02)
    time.sleep(0.3)  # the request is in flight, held by the server
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def _raw_bodies(received: list[bytes]) -> list[bytes]:
    """The bodies of the POSTs the endpoint received, as bytes."""
    return [r.split(b"\r\n\r\n", 1)[1] for r in received if r.startswith(b"POST ")]


def _bodies(received: list[bytes]) -> list[dict[str, object]]:
    return [json.loads(b) for b in _raw_bodies(received)]


def _stored(run_dir: Path) -> list[dict[str, object]]:
    with open_store(run_dir) as store:
        return store.llm_calls()


def _the_endpoint_saw_what_the_store_holds(server: FaultServer, run_dir: Path, unanswered: int) -> list[dict[str, object]]:
    calls = _stored(run_dir)
    # the same requests, byte for byte, in the order sent
    assert [str(c["request"]).encode("utf-8") for c in calls] == _raw_bodies(server.received())
    assert [c["answered"] for c in calls] == [True] * (len(calls) - unanswered) + [False] * unanswered
    assert all(c["error_kind"] == "unanswered" and not c["ok"] for c in calls[len(calls) - unanswered:])
    return calls


def _audit_reads_each(run_dir: Path, n: int) -> None:
    report = audit_run(run_dir, attacks=False)
    assert report.requests == n, report.format()
    with open_store(run_dir) as store:
        never = [int(c["id"]) for c in store.llm_calls() if not c["answered"]]
    assert never and report.unanswered == never, report.format()  # named, in the text and the JSON
    assert f"({len(never)} never answered: call{'s' if len(never) > 1 else ''} {', '.join(map(str, never))})" in report.format()
    assert report.to_json()["unanswered"] == never
    assert not report.leaks and not report.unverified, report.format()  # every request read and accounted for


def test_python_process_killed_mid_request(tmp_path: Path) -> None:
    script = textwrap.dedent("""
        import sys
        import ppprops

        with ppprops.create_study("CartPole", storage=sys.argv[1], method="pp-hardened", warmup=2, iterations=4, seed=3,
                                  llm={"base_url": sys.argv[2], "model": "m", "retries": 0},
                                  prompt={"form": "chat"}, evaluation={"final_episodes": 0, "select_top": 0}) as study:
            while True:  # the warm-up, two LLM trials answered; the third request is held, and the process killed in it
                trial = study.ask()
                study.tell(trial, 20.0 + trial.number, diagnostics={"episode_length": 20 + trial.number, "termination": "pole_fell"})
    """)
    run_dir = tmp_path / "study"
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=2, record=True, seed=1)) as server:
        proc = _launch([sys.executable, "-c", script, str(run_dir), server.base_url], tmp_path)
        _kill_once(proc, server, arrived=3)
        calls = _the_endpoint_saw_what_the_store_holds(server, run_dir, unanswered=1)
    assert len(calls) == 3 and [c["iteration"] for c in calls] == [0, 1, 2]
    _audit_reads_each(run_dir, 3)
    summary = run_summary(run_dir)
    assert summary["counts"]["llm_unanswered"] == 1 and summary["counts"]["llm_calls"] == 3
    assert summary["counts"]["llm_requests_failed"] == 0  # a request left in flight is not an endpoint fault
    assert "llm      1 request(s) sent and never answered" in format_summary(summary)


def _ppprops(args: list[str], cwd: Path, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ppprops", *args], cwd=cwd, input=stdin, capture_output=True, text=True, env=ENV,
                          timeout=300)


def test_shell_ask_killed_mid_request(tmp_path: Path) -> None:
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=1, record=True, seed=2)) as server:
        made = _ppprops(["study", "create", "--env", "CartPole", "--method", "pp", "--warmup", "1", "--iterations", "3", "--seed", "5",
                         "--final-episodes", "0", "--select-top", "0", "--prompt-form", "chat", "--base-url", server.base_url,
                         "--model", "m", "--retries", "0", "--out", "s"], tmp_path)  # fmt: skip
        assert made.returncode == 0, made.stderr
        for k in range(2):  # the warm-up trial, then the first LLM trial (its request answered)
            trial = json.loads(_ppprops(["ask", "s"], tmp_path).stdout)
            told = _ppprops(["tell", "s", str(trial["trial"]), "--return", str(15 + k), "--diagnostic", f"episode_length={15 + k}",
                             "--diagnostic", "termination=pole_fell"], tmp_path)  # fmt: skip
            assert told.returncode == 0, told.stderr
        proc = _launch([sys.executable, "-m", "ppprops", "ask", "s"], tmp_path)  # its request is held; SIGKILL in it
        _kill_once(proc, server, arrived=2)
        calls = _the_endpoint_saw_what_the_store_holds(server, tmp_path / "s", unanswered=1)
    assert [c["iteration"] for c in calls] == [0, 1]
    _audit_reads_each(tmp_path / "s", 2)
    shown = _ppprops(["show", "s"], tmp_path)
    assert shown.returncode == 0 and "1 request(s) sent and never answered" in shown.stdout, shown.stdout + shown.stderr
    audit = _ppprops(["audit", "s", "--no-simulate"], tmp_path)
    assert "2 requests" in audit.stdout, audit.stdout + audit.stderr


def test_a_run_killed_in_a_round_of_parallel_requests_then_resumed(tmp_path: Path) -> None:
    """``ppprops run --parallel 4``: the first round's four requests answered, the second round's four
    held, then SIGKILL. The store holds the eight the endpoint received (four unanswered), the audit
    reads and names each; ``resume`` finishes the run and the counts still agree."""
    args = ["run", "--env", "CartPole", "--method", "pp-hardened", "--warmup", "2", "--iterations", "12", "--parallel", "4",
            "--seed", "4", "--final-episodes", "0", "--select-top", "0", "--prompt-form", "chat", "--retries", "0", "--out", "r"]
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=4, record=True, seed=3)) as server:
        proc = _launch([sys.executable, "-m", "ppprops", *args, "--base-url", server.base_url, "--model", "m"], tmp_path)
        _kill_once(proc, server, arrived=8)
        raw = _raw_bodies(server.received())
        calls = _stored(tmp_path / "r")
        # the same eight bodies, byte for byte (a round's four leave in any order)
        assert sorted(raw) == sorted(str(c["request"]).encode("utf-8") for c in calls) and len(calls) == 8
        assert [c["answered"] for c in calls] == [True] * 4 + [False] * 4
        _audit_reads_each(tmp_path / "r", 8)
        server.release()
        resumed = _ppprops(["resume", "r"], tmp_path)
        assert resumed.returncode == 0, resumed.stderr
        raw = _raw_bodies(server.received())
    calls = _stored(tmp_path / "r")
    assert sorted(raw) == sorted(str(c["request"]).encode("utf-8") for c in calls) and len(calls) == len(raw) >= 12
    with open_store(tmp_path / "r") as store:
        assert store.status() == "finished" and sum(c.source == "llm" for c in store.candidates()) == 12
    report = audit_run(tmp_path / "r", attacks=False)
    assert report.requests == len(raw) and not report.leaks and not report.unverified, report.format()
    assert report.unanswered == [int(c["id"]) for c in calls if not c["answered"]]  # the four left by the kill


def test_requests_in_flight_together_killed(tmp_path: Path) -> None:
    """P = 3 requests sent at once from three threads through one recording client, all held, then
    SIGKILL: the store holds the three the endpoint received, each unanswered."""
    script = textwrap.dedent("""
        import sys, threading
        from ppprops.llm.client import EndpointClient
        from ppprops.llm.recording import RecordingLLM
        from ppprops.llm.settings import LLMConfig
        from ppprops.store import RunStore
        from support import chat_request

        store = RunStore(sys.argv[1])
        rec = RecordingLLM(EndpointClient(LLMConfig(base_url=sys.argv[2], model="m", transport_retries=0)), store)
        threads = [threading.Thread(target=rec.send, args=(chat_request([{"role": "user", "content": f"request {i}"}], 3,
                                                                        iteration=i),)) for i in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    """)
    db = tmp_path / "run.sqlite"
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=0, record=True)) as server:
        proc = _launch([sys.executable, "-c", script, str(db), server.base_url], tmp_path)
        _kill_once(proc, server, arrived=3)
        raw = _raw_bodies(server.received())
    sent = [json.loads(b) for b in raw]
    calls = _stored(tmp_path)
    assert sorted(raw) == sorted(str(c["request"]).encode("utf-8") for c in calls)  # byte for byte, in any order
    assert sorted(c["iteration"] for c in calls) == [0, 1, 2] and not any(c["answered"] for c in calls)
    assert sorted(b["messages"][0]["content"] for b in sent) == ["request 0", "request 1", "request 2"]  # type: ignore[index]


def test_a_try_that_cannot_be_written_ahead_is_never_sent(tmp_path: Path) -> None:
    """The body is written ahead from inside the HTTP client's request hook; when the store refuses
    it, the request does not leave, and the store's own error reaches the caller (not a dropped
    connection to retry)."""
    class FullDisk(RunStore):
        def begin_llm_call(self, *args: object, **kwargs: object) -> int:
            raise StoreError("cannot write the run store: disk full")

    with FaultServer(FaultConfig(fault_rate=0.0, record=True)) as server:
        client = EndpointClient(LLMConfig(base_url=server.base_url, model="m", transport_retries=2))
        rec = RecordingLLM(client, FullDisk(tmp_path / "run.sqlite"))
        with pytest.raises(StoreError, match="disk full"):
            rec.send(chat_request([{"role": "user", "content": "hello"}], 3))
        client.close()
        assert _raw_bodies(server.received()) == []
