"""Endpoint faults: every transient fault is retried with backoff within a bound, each try is
counted, Retry-After is honoured up to its cap, and the fault server itself behaves as specified."""

from __future__ import annotations

import http.client
import json
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import pytest

from ppprops.config import LLMConfig
from ppprops.llm.client import EndpointClient, LLMRejected, LLMUnavailable
from ppprops.testing.fault_server import ALL_KINDS, FaultConfig, FaultServer, requested_dim
from ppprops.wire.forms import params_grammar, params_schema

from support import chat_request

MSG = [{"role": "user", "content": "Answer with JSON only, exactly in this form, with 6 numbers: ..."}]


@contextmanager
def client_for(cfg: FaultConfig, **llm: object) -> Iterator[tuple[EndpointClient, FaultServer]]:
    settings: dict[str, object] = dict(
        timeout_s=0.5, transport_retries=2, retry_base_s=0.01, retry_max_s=0.05, structured="json_schema"
    )
    settings.update(llm)
    with FaultServer(cfg) as server:
        conf = LLMConfig(base_url=server.base_url, model="m", **settings)  # type: ignore[arg-type]
        client = EndpointClient(conf, base_url=server.base_url, model="m", api_key="k", grammar_ok=False)
        try:
            yield client, server
        finally:
            client.close()


@pytest.mark.parametrize(
    "kind,error_kind",
    [("http_429", "rate_limited"), ("http_500", "http_500"), ("http_503", "http_503"), ("drop", "dropped"),
     ("reset", "dropped"), ("bad_json", "bad_response"), ("timeout", "timeout"), ("error_body", "http_502")],
)
def test_transient_fault_is_retried_to_the_bound_and_every_try_is_kept(kind: str, error_kind: str) -> None:
    cfg = FaultConfig(fault_rate=1.0, kinds=(kind,), timeout_s=10.0, retry_after_s=0.01)  # stalls past every try
    with client_for(cfg) as (client, server):
        with pytest.raises(LLMUnavailable) as info:
            client.send(chat_request(MSG, 6))
        assert server.stats()["requests"] == 3  # 1 try + 2 retries, no more
    tries = info.value.failures
    assert [t.retry for t in tries] == [0, 1, 2]
    assert all(not t.ok and t.error_kind == error_kind for t in tries)
    assert info.value.kind == error_kind and "3 times in a row" in str(info.value)
    if kind == "timeout":  # each timed-out try of a request waits twice as long the next time
        assert [re.search(r"within (\S+) s", t.error or "").group(1) for t in tries] == ["0.5", "1", "2"]  # type: ignore[union-attr]


def test_a_fault_then_success_returns_the_answer_with_the_failed_tries() -> None:
    # find a seed whose sequence starts with a fault, then passes
    for seed in range(50):
        cfg = FaultConfig(fault_rate=0.5, kinds=("http_503",), seed=seed)
        with client_for(cfg, transport_retries=4) as (client, server):
            try:
                ex = client.send(chat_request(MSG, 6))
            except LLMUnavailable:
                continue
            if ex.failures:
                assert ex.ok and ex.retry == len(ex.failures) and json.loads(ex.content or "")["params"]
                assert [f.error_kind for f in ex.failures] == ["http_503"] * len(ex.failures)
                assert server.stats()["requests"] == len(ex.failures) + 1
                return
    pytest.fail("no seed gave a fault followed by a success")


def test_retry_after_is_honoured_and_capped() -> None:
    """The waits the client takes between tries, as it asks for them (``EndpointClient.sleep``), not
    as a loaded machine's clock measures them."""
    cfg = FaultConfig(fault_rate=1.0, kinds=("http_429",), retry_after_s=0.4)
    with client_for(cfg, transport_retries=1, retry_after_cap_s=10.0) as (client, _):
        waits: list[float] = []
        client.sleep = waits.append
        with pytest.raises(LLMUnavailable) as info:
            client.send(chat_request(MSG, 6))
        assert waits == [0.4]  # waited what the server asked, once: one retry
        assert "Retry-After 0.4 s" in (info.value.failures[0].error or "")
    cfg = FaultConfig(fault_rate=1.0, kinds=("http_429",), retry_after_s=30.0)
    with client_for(cfg, transport_retries=1, retry_after_cap_s=0.1) as (client, _):
        waits = []
        client.sleep = waits.append
        with pytest.raises(LLMUnavailable):
            client.send(chat_request(MSG, 6))
        assert waits == [0.1]  # the cap, not the 30 s asked for


def test_backoff_grows_exponentially_with_jitter_and_a_ceiling() -> None:
    conf = LLMConfig(base_url="http://127.0.0.1:9/v1", model="m", retry_base_s=1.0, retry_max_s=8.0)
    client = EndpointClient(conf, base_url="http://127.0.0.1:9/v1", model="m", api_key="k", grammar_ok=False)
    waits = {r: [client.backoff(r, None) for _ in range(200)] for r in range(6)}
    client.close()
    for r, ws in waits.items():
        d = min(8.0, 2.0**r)
        assert all(d / 2 <= w <= d for w in ws)  # equal jitter: half fixed, half random
        assert len(set(ws)) > 100  # really random
    assert max(waits[5]) <= 8.0 and min(waits[3]) > max(waits[1])


def test_refused_connection_is_its_own_kind() -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}/v1"
    conf = LLMConfig(base_url=url, model="m", transport_retries=1, retry_base_s=0.01, retry_max_s=0.01)
    client = EndpointClient(conf, base_url=url, model="m", api_key="k", grammar_ok=False)
    with pytest.raises(LLMUnavailable) as info:
        client.send(chat_request(MSG, 6))
    client.close()
    assert [f.error_kind for f in info.value.failures] == ["refused", "refused"]


def test_a_permanent_http_error_is_not_retried() -> None:
    with FaultServer(FaultConfig(fault_rate=0.0)) as server:
        url = server.base_url.replace("/v1", "/wrong/v1")  # 404 for every request
        conf = LLMConfig(base_url=url, model="m", transport_retries=3, retry_base_s=0.01)
        client = EndpointClient(conf, base_url=url, model="m", api_key="k", grammar_ok=False)
        with pytest.raises(LLMRejected) as info:
            client.send(chat_request(MSG, 6))
        client.close()
    assert [f.error_kind for f in info.value.failures] == ["http_404"]


def test_fault_server_reads_D_from_schema_grammar_or_prompt_and_answers_it() -> None:
    assert requested_dim({"response_format": {"json_schema": {"schema": params_schema(7)}}}) == 7
    assert requested_dim({"grammar": params_grammar(9)}) == 9
    assert requested_dim({"grammar": params_grammar(1)}) == 1
    assert requested_dim({"messages": [{"role": "user", "content": "Answer with JSON only, with 12 numbers: x"}]}) == 12
    assert requested_dim({"messages": [{"role": "user", "content": "no length here"}]}) is None
    for structured in ("json_schema", "grammar", "none"):
        with client_for(FaultConfig(fault_rate=0.0), structured=structured) as (client, _):
            ex = client.send(chat_request(MSG, 6))
        assert ex.ok and len(json.loads(ex.content or "")["params"]) == 6


def test_fault_server_is_seeded_and_stops_by_itself() -> None:
    def sequence(seed: int) -> dict[str, int]:
        with client_for(FaultConfig(fault_rate=0.5, kinds=ALL_KINDS, seed=seed, timeout_s=0.6), transport_retries=0) as (c, s):
            for _ in range(12):
                try:
                    c.send(chat_request(MSG, 6))
                except LLMUnavailable:
                    pass
            return dict(s.stats()["injected"])

    assert sequence(1) == sequence(1) != sequence(2)
    with FaultServer(FaultConfig(fault_rate=0.0, max_requests=2, max_seconds=600)) as server:
        body = json.dumps({"model": "m", "messages": MSG}).encode()
        codes = []
        for _ in range(3):
            req = urllib.request.Request(
                server.base_url + "/chat/completions", data=body, headers={"Content-Type": "application/json"}
            )
            try:
                with urllib.request.urlopen(req, timeout=5) as resp:
                    codes.append(resp.status)
            except urllib.error.HTTPError as e:
                codes.append(e.code)
        assert codes == [200, 200, 503]
        # stopped by the request budget (just after its 503 goes out), long before the 600 s
        assert server._state.stop.wait(120)
        server.wait()  # returns
    with FaultServer(FaultConfig(max_seconds=0.3)) as server:
        t0 = time.monotonic()
        server.wait()  # returns once the 0.3 s are up (a server that never stops: the test's timeout)
        assert time.monotonic() - t0 >= 0.3


def _post(url: str, body: bytes, timeout: float = 10) -> tuple[int, bytes]:
    req = urllib.request.Request(url, data=body, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


CHAT = json.dumps({"model": "m", "messages": MSG}).encode()


def test_fault_server_fixed_answer_is_every_healthy_answer() -> None:
    body = {"error": {"message": "You exceeded your current quota", "code": "insufficient_quota"}}
    with FaultServer(FaultConfig(fault_rate=0.0, fixed_status=429, fixed_body=json.dumps(body))) as server:
        got = [_post(server.base_url + "/chat/completions", CHAT) for _ in range(2)]
        assert server.stats()["requests"] == 2 and server.stats()["passed"] == 2
    assert got == [(429, json.dumps(body).encode())] * 2
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("http_503",), fixed_status=200)) as server:  # faults still come first
        assert _post(server.base_url + "/chat/completions", CHAT)[0] == 503
    for bad in (dict(fixed_status=99), dict(fixed_status=200, fixed_body="not json"),
                dict(fixed_status=200, personas=("plain",)), dict(fixed_status=200, upstream="http://127.0.0.1:9/v1"),
                dict(hold_after=-1)):
        with pytest.raises(ValueError):
            FaultServer(FaultConfig(**bad))  # type: ignore[arg-type]


def test_fault_server_holds_requests_after_the_first_n_until_released_or_stopped() -> None:
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=1, max_seconds=60)) as server:
        assert _post(server.base_url + "/chat/completions", CHAT)[0] == 200  # the first is answered
        with ThreadPoolExecutor(2) as pool:
            held = [pool.submit(_post, server.base_url + "/chat/completions", CHAT) for _ in range(2)]
            deadline = time.monotonic() + 10
            while server.stats()["requests"] < 3 and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.2)
            assert server.stats()["requests"] == 3 and not any(f.done() for f in held)  # arrived, held open
            assert server.stats()["most_in_flight"] == 2
            server.release()
            assert [f.result(timeout=10)[0] for f in held] == [200, 200]
        assert _post(server.base_url + "/chat/completions", CHAT)[0] == 200  # released for good
    with FaultServer(FaultConfig(fault_rate=0.0, hold_after=0, max_seconds=60)) as server:
        with ThreadPoolExecutor(1) as pool:
            dropped = pool.submit(_post, server.base_url + "/chat/completions", CHAT)
            while server.stats()["requests"] < 1:
                time.sleep(0.02)
            server.stop()  # a held request's connection is dropped when the server stops
            assert not any(t.is_alive() for t in server._threads)  # stop did not give up waiting on the held one
            with pytest.raises((urllib.error.URLError, ConnectionError, http.client.HTTPException)):
                dropped.result(timeout=10)


def test_fault_server_records_each_request_byte_for_byte_and_counts_those_in_flight() -> None:
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("delay",), delay_max_s=0.0, record=True)) as server:
        _post(server.base_url + "/chat/completions", CHAT)
        _post(server.base_url + "/chat/completions", CHAT)
        with urllib.request.urlopen(server.base_url + "/stats", timeout=5) as resp:  # the server's own route: not kept
            assert json.loads(resp.read())["most_in_flight"] == 1  # one after the other
        got = server.received()
    assert len(got) == 2 and all(r.startswith(b"POST /v1/chat/completions HTTP/1.1\r\n") for r in got)
    assert [r.split(b"\r\n\r\n", 1)[1] for r in got] == [CHAT, CHAT]
    assert b"\r\nContent-Type: application/json\r\n" in got[0]
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("delay",), delay_max_s=0.0)) as server:  # record off: nothing kept
        _post(server.base_url + "/chat/completions", CHAT)
        assert server.received() == []
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("timeout",), timeout_s=0.5)) as server:
        with ThreadPoolExecutor(3) as pool:
            stalled = [pool.submit(_post, server.base_url + "/chat/completions", CHAT) for _ in range(3)]
        assert all(isinstance(f.exception(), http.client.RemoteDisconnected) for f in stalled)  # each timed out
        assert server.stats()["most_in_flight"] == 3  # all three stalled together


def test_fault_server_command_line_holds_releases_and_writes_the_requests(tmp_path: Path) -> None:
    requests_file = tmp_path / "requests.json"
    proc = subprocess.Popen([sys.executable, "-m", "ppprops.testing.fault_server", "--fault-rate", "0", "--hold-after", "0",
                             "--fixed-status", "418", "--fixed-body", '{"teapot": true}', "--requests-file", str(requests_file),
                             "--max-seconds", "60"], stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().split()[1]
        with ThreadPoolExecutor(1) as pool:
            held = pool.submit(_post, url + "/chat/completions", CHAT)
            time.sleep(0.5)
            assert not held.done()
            assert _post(url + "/release", b"") == (200, b'{"released": true}')
            assert held.result(timeout=10) == (418, b'{"teapot": true}')
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0 and json.loads(out.splitlines()[-1])["requests"] == 1
    recorded = json.loads(requests_file.read_text())
    assert len(recorded) == 1 and recorded[0].startswith("POST /v1/chat/completions ") and recorded[0].endswith(CHAT.decode())


@pytest.mark.llm
def test_fault_server_passes_healthy_requests_to_the_embedded_model(embedded_server) -> None:  # type: ignore[no-untyped-def]
    from ppprops.llm.embedded import MODEL_ALIAS

    cfg = FaultConfig(fault_rate=0.5, kinds=("http_503", "reset", "http_429"), retry_after_s=0.01, seed=3,
                      upstream=embedded_server.base_url)  # seed 3: one fault, then healthy requests
    with FaultServer(cfg) as server:
        conf = LLMConfig(base_url=server.base_url, model=MODEL_ALIAS, transport_retries=4, retry_base_s=0.01, retry_max_s=0.02)
        client = EndpointClient(conf, base_url=server.base_url, model=MODEL_ALIAS, api_key="k", grammar_ok=True)
        ex = client.send(chat_request(MSG, 3), seed=0)
        client.close()
        stats = server.stats()
    assert stats["passed"] == 1 and stats["injected_total"] == 1 and len(ex.failures) == 1
    assert ex.ok and len(json.loads(ex.content or "")["params"]) == 3  # the model's answer, shaped by the grammar sent through
