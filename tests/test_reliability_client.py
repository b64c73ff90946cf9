"""Endpoint faults: every transient fault is retried with backoff within a bound, each try is
counted, Retry-After is honoured up to its cap, and the fault server itself behaves as specified."""

from __future__ import annotations

import json
import re
import socket
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager

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
    cfg = FaultConfig(fault_rate=1.0, kinds=("http_429",), retry_after_s=0.4)
    with client_for(cfg, transport_retries=1, retry_after_cap_s=10.0) as (client, _):
        t0 = time.perf_counter()
        with pytest.raises(LLMUnavailable) as info:
            client.send(chat_request(MSG, 6))
        assert time.perf_counter() - t0 >= 0.4  # waited what the server asked
        assert "Retry-After 0.4 s" in (info.value.failures[0].error or "")
    cfg = FaultConfig(fault_rate=1.0, kinds=("http_429",), retry_after_s=30.0)
    with client_for(cfg, transport_retries=1, retry_after_cap_s=0.1) as (client, _):
        t0 = time.perf_counter()
        with pytest.raises(LLMUnavailable):
            client.send(chat_request(MSG, 6))
        assert time.perf_counter() - t0 < 5.0  # not the 30 s asked for


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
    with FaultServer(FaultConfig(fault_rate=0.0, max_requests=2, max_seconds=30)) as server:
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
        t0 = time.monotonic()
        server.wait()  # returns: the request budget is spent
        assert time.monotonic() - t0 < 5
    with FaultServer(FaultConfig(max_seconds=0.3)) as server:
        t0 = time.monotonic()
        server.wait()
        assert time.monotonic() - t0 < 5


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
