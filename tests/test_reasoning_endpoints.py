"""Reasoning models and real endpoints, one test (at least) per row of the table in docs/endpoints.md.

Each test runs a real CartPole search against the fault server answering as a given server and
model (``ppprops.testing.personas``) and asserts which vector was evaluated: every LLM
candidate's encoded params equal the new vector the persona proposed, in order, and none equals
an earlier candidate at the precision the prompt prints (a quoted or restated history entry);
or it asserts the exact line and exit code the run stops with.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.client.hardening import codec_for
from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig
from ppprops.errors import LLMError
from ppprops.llm.client import REASONING_ROOM, EndpointClient, LLMRejected, LLMUnavailable, default_max_tokens
from ppprops.proposers.base import clip_to_box
from ppprops.runner import load_run, start
from ppprops.store import Candidate, open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer
from ppprops.testing.personas import HARMONY_TEMPLATE_ERROR
from ppprops.wire.numbers import fmt_vector

from support import chat_request, make_config

D = 10  # CartPole: (4 + 1) * 2
A = 2.0  # every a_j: encoded = 2 * raw, so a persona's answers in [-3, 3] decode inside the box, unclipped
PLAIN_BUDGET = default_max_tokens(D, explanation=True)  # 616: a chat request to an endpoint other than the embedded model


@dataclass
class Run:
    out: Path
    candidates: list[Candidate]
    calls: list[dict[str, Any]]
    adaptations: list[dict[str, Any]]
    answers: list[list[float]]  # the new vectors the persona proposed, in order
    stats: dict[str, Any]

    @property
    def llm(self) -> list[Candidate]:
        return [c for c in self.candidates if c.source == "llm"]

    def requests(self) -> list[dict[str, Any]]:
        return [json.loads(c["request"]) for c in self.calls]


def _llm(server: FaultServer, **kw: Any) -> LLMConfig:
    # A timeout far past any answer's time: at 5 s, an answer slowed to 0.5 s by a loaded machine (the client's TIMED_SHARE
    # of it) fitted a longer timeout, an adaptation these tests do not ask for (llm.client: the timeout fitted to the rate).
    settings: dict[str, Any] = dict(timeout_s=120.0, transport_retries=1, retry_base_s=0.01, retry_max_s=0.02)
    settings.update(kw)
    return LLMConfig(base_url=server.base_url, model="m", **settings)


def run(tmp_path: Path, *personas: str, iterations: int = 4, llm: dict[str, Any] | None = None,
        server: dict[str, Any] | None = None, **config: Any) -> Run:
    out = tmp_path / "run"
    with FaultServer(FaultConfig(fault_rate=0.0, personas=personas, **(server or {}))) as srv:
        cfg = make_config(warmup=3, iterations=iterations, final_episodes=0, llm=_llm(srv, **(llm or {})), **config)
        start(cfg, out, secrets=Secrets(run_id="reasoning", a=np.full(D, A), c=1.0))
        answers = [a for _, _, a in srv.answers()]
        stats = srv.stats()
    store = open_store(out)
    try:
        return Run(out, store.candidates(), store.llm_calls(), store.llm_adaptations(), answers, stats)
    finally:
        store.close()


def printed(values: Any) -> str:
    return fmt_vector(list(values), 2, digits=3, sep=",")  # the prompt's list form (decimals 2, 3 digits)


def assert_no_history_vector(cands: list[Candidate]) -> None:
    """No LLM candidate equals an earlier candidate as the prompt prints it."""
    for i, c in enumerate(cands):
        if c.source == "llm":
            assert all(printed(c.params_enc) != printed(e.params_enc) for e in cands[:i]), c.index


def assert_evaluated_the_answers(r: Run, n: int = 4) -> None:
    """The LLM candidates are exactly the persona's proposals, in order, and none is a history vector."""
    assert len(r.llm) == n and len(r.answers) == n, (len(r.llm), r.answers)
    for c, a in zip(r.llm, r.answers):
        assert c.params_enc == pytest.approx(a, abs=1e-12)
        assert c.clipped == 0
    assert_no_history_vector(r.candidates)


def cli_run(tmp_path: Path, url: str, *extra: str) -> list[str]:
    return ["run", "--env", "CartPole", "--method", "pp", "--warmup", "3", "--iterations", "2", "--final-episodes", "0",
            "--out", str(tmp_path / "run"), "--quiet", "--base-url", url, "--model", "m", "--retries", "1",
            "--retry-base-delay", "0.01", "--retry-max-delay", "0.02", *extra]


def decoded(out: Path, answer: list[float]) -> np.ndarray:
    """What the run evaluates for an encoded answer: decoded with its own secrets, clipped to the box."""
    store, config, secrets = load_run(out)
    store.close()
    theta = codec_for(secrets, config.make_task(), config.encoding).decode(np.asarray(answer))
    return clip_to_box(theta, config.box)[0]


def json_server(status: int, doc: Any) -> FaultServer:
    """The fault server answering every request with one fixed status and JSON body (a server quirk)."""
    return FaultServer(FaultConfig(fault_rate=0.0, fixed_status=status, fixed_body=json.dumps(doc)))


# -- row 1: out of max_tokens while reasoning ----------------------------------------------------
def test_row1_cut_off_answer_is_never_used_and_the_budget_grows_for_reasoning(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    r = run(tmp_path, "vllm_gpt_oss")
    first = r.calls[0]
    assert json.loads(first["request"])["max_tokens"] == PLAIN_BUDGET
    assert first["content"] is None and first["parse_error"] == "length" and "[" in first["reasoning"]  # quotes history
    assert [a["change"] for a in r.adaptations] == [
        f"max_tokens raised from {PLAIN_BUDGET} to {PLAIN_BUDGET + 8192}: the endpoint returns reasoning"]
    assert all(json.loads(c["request"])["max_tokens"] == PLAIN_BUDGET + 8192 for c in r.calls[1:])
    assert_evaluated_the_answers(r)
    assert main(["show", str(r.out)]) == 0
    assert "endpoint adapted at LLM iteration 0: max_tokens raised" in capsys.readouterr().out


def test_row1_with_a_fixed_max_tokens_every_cut_off_answer_falls_back_naming_the_flag(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    r = run(tmp_path, "vllm_gpt_oss", iterations=2, llm=dict(max_tokens=100))
    assert [c["parse_error"] for c in r.calls] == ["length"] * 6 and r.adaptations == [] and r.answers == []
    assert [c.source for c in r.candidates[3:]] == ["fallback", "fallback"]
    note = "after length (answers were cut off at the token limit: raise --max-tokens or lower --reasoning-effort)"
    assert all(c.note == note for c in r.candidates[3:])
    assert_no_history_vector(r.candidates)
    assert main(["show", str(r.out)]) == 0
    out = capsys.readouterr().out
    assert "answers  cut off at the token limit: raise --max-tokens (or lower --reasoning-effort)" in out
    assert "fallback length x2" in out


def test_row1_reasoning_effort_leaves_room_for_reasoning_from_the_first_request(tmp_path: Path) -> None:
    r = run(tmp_path, "vllm_gpt_oss", llm=dict(reasoning_effort="low"))
    assert json.loads(r.calls[0]["request"])["max_tokens"] == PLAIN_BUDGET + REASONING_ROOM["low"]
    assert json.loads(r.calls[0]["request"])["reasoning_effort"] == "low"
    assert len(r.calls) == 4 and not any(c["parse_error"] for c in r.calls) and r.adaptations == []
    assert_evaluated_the_answers(r)


# -- row 2: a restated history entry before the requested object -----------------------------------
@pytest.mark.parametrize("style", ["list", "indexed"])
def test_row2_the_requested_params_object_wins_over_a_restated_history_entry(tmp_path: Path, style: str) -> None:
    r = run(tmp_path, "restates_history", prompt_params=style)
    assert all("params[0]: " in c["content"] for c in r.calls)  # every answer restated an entry first
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r)


# -- row 3: R1-style reasoning up to a lone closing tag ----------------------------------------------
def test_row3_reasoning_up_to_a_lone_closing_tag_is_reasoning(tmp_path: Path) -> None:
    r = run(tmp_path, "r1_open_think")
    assert all("<think>" not in c["content"] and "</think>" in c["content"] for c in r.calls)
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r)


def test_row3_closed_think_tags_in_content(tmp_path: Path) -> None:
    r = run(tmp_path, "r1_think_tags")
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r)


# -- row 4: harmony channel markup ---------------------------------------------------------------------
def test_row4_the_final_harmony_channel_is_the_answer(tmp_path: Path) -> None:
    r = run(tmp_path, "harmony_markup", llm=dict(reasoning_effort="low"))
    assert all(c["content"].startswith("<|channel|>analysis<|message|>") for c in r.calls)
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r)


def test_row4_corrections_never_echo_markup_so_the_template_never_refuses(tmp_path: Path) -> None:
    r = run(tmp_path, "harmony_markup_repeats_once", llm=dict(reasoning_effort="low"))
    assert all(c["ok"] for c in r.calls)  # no HTTP 500 from the chat template
    assert [c["parse_error"] for c in r.calls] == ["repeats_history", None] * 4
    for req in r.requests()[1::2]:  # each correction
        roles = [m["role"] for m in req["messages"]]
        assert roles == ["user", "assistant", "user"]
        assert "<|" not in req["messages"][1]["content"] and req["messages"][1]["content"].startswith('{"params": [')
        assert "could not be used: those params are a policy already in the history" in req["messages"][2]["content"]
    assert_evaluated_the_answers(r)


def test_row4_a_500_saying_the_request_is_invalid_is_not_retried() -> None:
    with FaultServer(FaultConfig(fault_rate=0.0, personas=("harmony_markup",))) as server:
        conf = LLMConfig(base_url=server.base_url, model="m", transport_retries=4, retry_base_s=0.01)
        client = EndpointClient(conf, base_url=server.base_url, model="m", api_key="k", grammar_ok=False)
        messages = [{"role": "user", "content": "Answer with JSON only, exactly in this form, with 10 numbers: x"},
                    {"role": "assistant", "content": "<|channel|>analysis<|message|>hm<|end|>"},
                    {"role": "user", "content": "again"}]
        with pytest.raises(LLMRejected) as info:
            client.send(chat_request(messages, 10))
        client.close()
        assert server.stats()["requests"] == 1
    (tried,) = info.value.failures
    assert tried.error_kind == "invalid_request"
    assert str(info.value) == (f"LLM endpoint refused the request: invalid_request: HTTP 500 from {server.base_url}"
                               f"/chat/completions: {HARMONY_TEMPLATE_ERROR}")


# -- row 5: content null, the answer in the reasoning ------------------------------------------------
def test_row5_the_last_explicit_answer_in_the_reasoning_is_used_and_marked(tmp_path: Path) -> None:
    r = run(tmp_path, "vllm_gpt_oss_final_in_reasoning", llm=dict(reasoning_effort="low"))
    assert all(c["content"] is None and c["answer_source"] == "reasoning" for c in r.calls)
    assert all("The best so far is [" in c["reasoning"] for c in r.calls)  # a quoted history list first
    assert all(c.note == "answer taken from the reasoning text" for c in r.llm)
    assert_evaluated_the_answers(r)


# -- rows 6 and 7: refused parameters ----------------------------------------------------------------------
def test_row6_a_422_text_body_refusing_json_schema_drops_the_schema_once(tmp_path: Path) -> None:
    r = run(tmp_path, "deepseek_reasoner")
    first = r.calls[0]
    assert not first["ok"] and first["error_kind"] == "http_422"
    assert "response_format.type `json_schema` is unavailable now" in first["error"]
    assert "; adapted: dropped the JSON schema (plain answers)" in first["error"]
    (change,) = [a["change"] for a in r.adaptations if "schema" in a["change"]]
    assert change.startswith("dropped the JSON schema (plain answers) (after HTTP 422: Failed to deserialize the JSON")
    assert "response_format" in r.requests()[0] and not any("response_format" in q for q in r.requests()[1:])
    assert_evaluated_the_answers(r)


def test_row6_with_structured_json_schema_asked_for_the_run_stops_with_the_servers_words(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    with FaultServer(FaultConfig(fault_rate=0.0, personas=("deepseek_reasoner",))) as server:
        code = main(cli_run(tmp_path, server.base_url, "--structured", "json_schema"))
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"ppprops: error: LLM endpoint refused the request: http_422: HTTP 422 from {server.base_url}"
                          "/chat/completions: Failed to deserialize the JSON body into the target type: response_format:")
    assert "(--structured json_schema was asked for; use --structured auto or none); the run is saved" in err


def test_row7_a_400_naming_seed_drops_seed_for_the_rest_of_the_run_and_keeps_the_schema(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    r = run(tmp_path, "gemini_openai")
    assert [c["ok"] for c in r.calls] == [False, True, True, True, True]
    assert r.calls[0]["error_kind"] == "bad_request" and 'Unknown name "seed": Cannot find field.' in r.calls[0]["error"]
    assert [a["change"] for a in r.adaptations] == [
        'dropped seed (after HTTP 400: Invalid JSON payload received. Unknown name "seed": Cannot find field.)']
    assert "seed" in r.requests()[0] and all("seed" not in q and "response_format" in q for q in r.requests()[1:])
    assert_evaluated_the_answers(r)
    assert main(["show", str(r.out), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["counts"]["request_adaptations"] == 1 and shown["llm_adaptations"][0]["change"].startswith("dropped seed")


# -- row 8: OpenAI reasoning models -------------------------------------------------------------------------
def test_row8_max_completion_tokens_and_no_temperature_and_no_http_error_as_a_correction(tmp_path: Path) -> None:
    r = run(tmp_path, "openai_reasoning", llm=dict(temperature=0.7))
    changes = [a["change"] for a in r.adaptations]
    assert changes[0].startswith("sent max_completion_tokens instead of max_tokens (after HTTP 400: Unsupported parameter")
    assert changes[1].startswith("dropped temperature (after HTTP 400: Unsupported value: 'temperature' does not support 0.7")
    assert changes[2] == f"max_completion_tokens raised from {PLAIN_BUDGET} to {PLAIN_BUDGET + 8192}: the endpoint returns reasoning"
    last = r.requests()[-1]
    assert "max_tokens" not in last and "temperature" not in last and last["max_completion_tokens"] == PLAIN_BUDGET + 8192
    for req in r.requests():  # no fake "(empty)" assistant turn, no HTTP error text ever sent to the model
        for m in req["messages"]:
            assert m["content"] != "(empty)" and "HTTP" not in m["content"] and "Unsupported" not in m["content"]
    assert_evaluated_the_answers(r)


# -- row 9: junk under a JSON schema (Ollama + gpt-oss) --------------------------------------------------------
def test_row9_auto_drops_the_schema_after_repeated_unusable_answers_under_it(tmp_path: Path) -> None:
    r = run(tmp_path, "ollama_gpt_oss", llm=dict(reasoning_effort="low"))
    assert [c["parse_error"] for c in r.calls[:2]] == ["no_numbers", "no_numbers"]
    assert [a["change"] for a in r.adaptations] == [  # the answers without it are better: it is not restored
        "dropped the JSON schema (plain answers): 2 answers in a row under it were unusable and not JSON, as from a server "
        "that ignores it; it comes back if the answers without it are no better"]
    assert all("response_format" in q for q in r.requests()[:2]) and not any("response_format" in q for q in r.requests()[2:])
    assert_evaluated_the_answers(r)


def test_row9_an_asked_for_schema_is_kept(tmp_path: Path) -> None:
    r = run(tmp_path, "ollama_gpt_oss", iterations=1, llm=dict(reasoning_effort="low", structured="json_schema"))
    assert r.adaptations == [] and all("response_format" in q for q in r.requests())
    assert [c.source for c in r.candidates[3:]] == ["fallback"]


# -- row 10: an error delivered with HTTP 200 ------------------------------------------------------------------
def test_row10_an_error_body_with_a_permanent_code_stops_with_the_providers_message(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("error_body",), error_body_code=404)) as server:
        code = main(cli_run(tmp_path, server.base_url))
        assert server.stats()["requests"] == 1  # not retried
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"ppprops: error: LLM endpoint refused the request: http_404: HTTP 200 with an error body "
                          f"(code 404) from {server.base_url}/chat/completions: Provider returned error (injected); ")
    s = json.loads((main(["show", str(tmp_path / "run"), "--json"]), capsys.readouterr().out)[1])
    assert s["counts"]["answer_failures"] == {} and s["counts"]["transport_failures"] == {"http_404": 1}


def test_row10_an_error_body_with_a_transient_code_is_retried_to_the_bound() -> None:
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("error_body",), error_body_code=502)) as server:
        conf = LLMConfig(base_url=server.base_url, model="m", transport_retries=2, retry_base_s=0.01, retry_max_s=0.02)
        client = EndpointClient(conf, base_url=server.base_url, model="m", api_key="k", grammar_ok=False)
        with pytest.raises(LLMUnavailable) as info:
            client.send(chat_request([{"role": "user", "content": "with 10 numbers"}], 10))
        client.close()
        assert server.stats()["requests"] == 3
    assert not isinstance(info.value, LLMRejected)
    assert all(t.error_kind == "http_502" and "Provider returned error (injected)" in (t.error or "") for t in info.value.failures)


# -- row 11: typographic minus signs ----------------------------------------------------------------------------
def test_row11_unicode_minus_and_en_dashes_read_as_minus_signs(tmp_path: Path) -> None:
    r = run(tmp_path, "unicode_minus")
    assert any("\u2212" in c["content"] for c in r.calls) and any("\u2013" in c["content"] for c in r.calls)
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r)
    assert min(min(c.params_enc) for c in r.llm) < 0


# -- row 12: --reasoning-effort none ------------------------------------------------------------------------------
def test_row12_reasoning_effort_none_is_accepted_and_sent(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    with FaultServer(FaultConfig(fault_rate=0.0, personas=("ollama_gpt_oss",))) as server:
        code = main(cli_run(tmp_path, server.base_url, "--reasoning-effort", "none", "--structured", "none"))
        answers = [a for _, _, a in server.answers()]
    assert code == 0, capsys.readouterr().err
    store = open_store(tmp_path / "run")
    calls, cands = store.llm_calls(), store.candidates()
    store.close()
    bodies = [json.loads(c["request"]) for c in calls]
    assert [(b["reasoning_effort"], b["max_tokens"]) for b in bodies] == [("none", PLAIN_BUDGET)] * 2
    assert all(c["reasoning"] is None for c in calls)  # thinking is off
    llm = [c for c in cands if c.source == "llm"]
    assert len(llm) == 2 and all(np.allclose(c.params, decoded(tmp_path / "run", a)) for c, a in zip(llm, answers))


# -- row 13: a wrong base URL --------------------------------------------------------------------------------------
def test_row13_a_base_url_ending_in_chat_completions_names_the_url_and_the_fix(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    with FaultServer(FaultConfig(fault_rate=0.0)) as server:
        url = server.base_url + "/chat/completions"
        code = main(cli_run(tmp_path, url))
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert err == (f"ppprops: error: LLM endpoint refused the request: http_404: HTTP 404 from {url}/chat/completions: "
                   f"no route /v1/chat/completions/chat/completions; --base-url must stop before /chat/completions "
                   f"(ppprops adds it): try --base-url {server.base_url}; the run is saved: continue with "
                   f"'ppprops resume {tmp_path / 'run'}'\n")


def test_row13_a_base_url_missing_v1_names_the_url_and_the_fix(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    with FaultServer(FaultConfig(fault_rate=0.0, v1_only=True)) as server:
        root = server.base_url.removesuffix("/v1")
        code = main(cli_run(tmp_path, root))
    err = capsys.readouterr().err
    assert code == 2 and err == (
        f"ppprops: error: LLM endpoint refused the request: http_404: HTTP 404 from {root}/chat/completions: "
        f"404 page not found; OpenAI-compatible APIs usually live under /v1: try --base-url {root}/v1; the run is "
        f"saved: continue with 'ppprops resume {tmp_path / 'run'}'\n")


# -- the rule behind the rows ----------------------------------------------------------------------------------------
def test_a_proposal_equal_to_a_history_entry_is_asked_again_and_counted(tmp_path: Path) -> None:
    r = run(tmp_path, "repeats_history_once")
    assert [c["parse_error"] for c in r.calls] == ["repeats_history", None] * 4
    retry = r.requests()[1]["messages"]
    assert retry[1]["role"] == "assistant" and "already in the history" in retry[2]["content"]
    assert_evaluated_the_answers(r)


def test_a_quota_exhausted_429_is_not_retried() -> None:
    body = {"error": {"message": "You exceeded your current quota, please check your plan and billing details.",
                      "type": "insufficient_quota", "param": None, "code": "insufficient_quota"}}
    with json_server(429, body) as server:
        url = server.base_url
        conf = LLMConfig(base_url=url, model="m", transport_retries=3, retry_base_s=0.01)
        client = EndpointClient(conf, base_url=url, model="m", api_key="k", grammar_ok=False)
        with pytest.raises(LLMRejected, match="quota_exhausted: HTTP 429 .*You exceeded your current quota"):
            client.send(chat_request([{"role": "user", "content": "x"}], 3))
        client.close()
        assert server.stats()["requests"] == 1


def test_a_400_naming_no_parameter_stops_at_once_with_the_servers_message() -> None:
    body = {"object": "error", "message": "This model's maximum context length is 4096 tokens. However, you requested "
            "5000 tokens. Please reduce the length of the messages or completion.", "type": "BadRequestError",
            "param": None, "code": 400}
    with json_server(400, body) as server:
        url = server.base_url
        conf = LLMConfig(base_url=url, model="m", transport_retries=3, retry_base_s=0.01)
        client = EndpointClient(conf, base_url=url, model="m", api_key="k", grammar_ok=False)
        with pytest.raises(LLMRejected, match="bad_request: HTTP 400 .*maximum context length is 4096 tokens"):
            client.send(chat_request([{"role": "user", "content": "x"}], 3))
        client.close()
        assert server.stats()["requests"] == 1


def test_run_level_stop_on_rejection_even_with_skip(tmp_path: Path) -> None:
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("error_body",), error_body_code=401)) as server:
        cfg = make_config(warmup=3, iterations=2, final_episodes=0, on_llm_failure="skip", llm=_llm(server))
        with pytest.raises(LLMError, match="code 401"):
            start(cfg, tmp_path / "run")
