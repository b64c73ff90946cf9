"""What real servers and real models did, replayed through the real client and a
real HTTP server (the fault server's personas, ``ppprops.testing.personas``), one test (at least)
per finding: a full context told apart from the answer budget, chat models that explain before
they answer, a slow CPU server against the timeout, a bullet list of too few numbers, llama.cpp
with a template that forces thinking open, the document form against a remote llama.cpp server,
and a run in which the LLM contributed nothing. Then the audit, through the real client, for
every request shape.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_attacks import seeded_secrets

from ppprops.cli import main
from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig
from ppprops.llm.client import EndpointClient, RequestShape, context_full, default_max_tokens
from ppprops.privacy.audit import audit_run
from ppprops.proposers.llm import HINTS
from ppprops.runner import start
from ppprops.store import Candidate, open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer, requested_dim
from ppprops.testing.personas import CONTEXT_TOKENS
from ppprops.wire.document import continuation_grammar

from support import chat_request, document_request, make_config, recorded_calls, tamper_call

D = 10  # CartPole
A = 2.0  # encoded = 2 * raw: the personas' answers in [-3, 3] decode inside the box
RUN_SEED = 913_572_448  # large: replaying the warm-up from the run seed is no channel here
CHAT_BUDGET = default_max_tokens(D, explanation=True)  # 616
DOCUMENT_BUDGET = default_max_tokens(D, labels=True)  # 104


@dataclass
class Run:
    out: Path
    candidates: list[Candidate]
    calls: list[dict[str, Any]]
    adaptations: list[str]
    answers: list[list[float]]  # the new vectors the personas proposed, in order

    @property
    def llm(self) -> list[Candidate]:
        return [c for c in self.candidates if c.source == "llm"]

    def requests(self) -> list[dict[str, Any]]:
        return [json.loads(c["request"]) for c in self.calls]


def run(tmp_path: Path, *personas: str, iterations: int = 2, llm: dict[str, Any] | None = None,
        method: str = "pp", name: str = "run", **config: Any) -> Run:
    out = tmp_path / name
    with FaultServer(FaultConfig(fault_rate=0.0, personas=personas)) as srv:
        settings: dict[str, Any] = dict(timeout_s=5.0, transport_retries=1, retry_base_s=0.01, retry_max_s=0.02)
        settings.update(llm or {})
        cfg = make_config(method=method, warmup=3, iterations=iterations, final_episodes=0, seed=RUN_SEED,
                          llm=LLMConfig(base_url=srv.base_url, model="m", **settings), **config)
        # fixed secrets: a run's outcome (and its audit verdict) repeats; pp-hardened's from its own distribution
        secrets = Secrets(run_id=name, a=np.full(D, A), c=1.0) if method == "pp" else (
            seeded_secrets(method, "CartPole", 0) if method == "pp-hardened" else None)
        start(cfg, out, secrets=secrets)
        answers = [a for _, _, a in srv.answers()]
    with open_store(out) as store:
        return Run(out, store.candidates(), store.llm_calls(), [a["change"] for a in store.llm_adaptations()], answers)


def assert_evaluated_the_answers(r: Run, n: int) -> None:
    """The LLM candidates are exactly the personas' proposals, in order."""
    assert len(r.llm) == n and len(r.answers) == n, (len(r.llm), r.answers)
    for c, a in zip(r.llm, r.answers):
        assert c.params_enc == pytest.approx(a, abs=1e-12)


def show(out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    capsys.readouterr()
    assert main(["show", str(out)]) == 0
    return capsys.readouterr().out


# -- a full context is not the answer budget ------------------------------------------------------------
def test_context_full_needs_fewer_tokens_than_the_budget_or_a_full_known_context() -> None:
    assert context_full(616, 4076, 20) and not context_full(616, 100, 616)
    assert not context_full(616, None, None)  # no usage: cannot tell, stays "length"
    assert context_full(None, 16300, 84, context_size=16384) and not context_full(None, 100, 84, context_size=16384)
    assert context_full(104, 16300, 104, context_size=16384)  # prompt and answer filled the embedded server's context


@pytest.mark.parametrize("form", ["chat", "document"])
def test_a_full_context_is_classified_context_full_with_its_own_hint(tmp_path: Path, form: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    r = run(tmp_path, "context_full", prompt_form=form)
    assert all(c["ok"] and json.loads(c["response"])["choices"][0]["finish_reason"] == "length" for c in r.calls)
    assert all(json.loads(c["response"])["usage"]["total_tokens"] == CONTEXT_TOKENS for c in r.calls)
    assert [c["parse_error"] for c in r.calls] == ["context_full"] * 6  # 2 iterations x (1 + 2 retries)
    note = f"after context_full ({HINTS['context_full']})"
    assert [c.note for c in r.candidates[3:]] == [note, note]
    assert "--max-tokens cannot help" in note and "--ctx-size" in note and "num_ctx" in note and "--top-k" in note
    out = show(r.out, capsys)
    assert "answers  cut off because the server's context was full (not --max-tokens)" in out
    assert "raise --max-tokens" not in out
    # nothing came from the LLM, and the summary says so before anything else
    assert out.splitlines()[3] == ("WARNING  every one of the 2 search candidates was a fallback: the LLM contributed "
                                   "nothing (context_full x2; the best policy plus noise was evaluated instead)")


def test_the_summary_says_when_most_search_candidates_were_fallbacks() -> None:
    from ppprops.summary import format_summary

    counts = {"candidates": 13, "warmup": 3, "llm": 4, "fallback": 6, "by_source": {"warmup": 3, "llm": 4, "fallback": 6},
              "llm_calls": 22, "answer_failures": {"length": 18}, "fallback_reasons": {"length": 6}}
    s = {"run_id": "x", "status": "finished", "env": "CartPole", "method": "pp", "seed": 0, "counts": counts,
         "best": None, "final_eval": None, "llm_calls": []}
    text = format_summary(s)
    assert ("WARNING  6 of the 10 search candidates were fallbacks: the LLM contributed little (length x6; the best "
            "policy plus noise was evaluated instead)") in text
    half = {**counts, "llm": 5, "fallback": 5, "by_source": {"warmup": 3, "llm": 5, "fallback": 5}}
    assert "WARNING" not in format_summary({**s, "counts": half})


# -- chat models that explain before they answer -----------------------------------------------------------
def test_chat_requests_leave_room_for_a_short_explanation(tmp_path: Path) -> None:
    r = run(tmp_path, "chatty_explainer", llm=dict(structured="none"))
    assert [q["max_tokens"] for q in r.requests()] == [CHAT_BUDGET, CHAT_BUDGET]
    assert all(c["content"].startswith("Looking at the history") for c in r.calls)
    assert not any(c["parse_error"] for c in r.calls)  # no answer cut off, no correction request
    assert_evaluated_the_answers(r, 2)


def test_the_embedded_model_and_the_document_form_get_no_explanation_room() -> None:
    chat, document = chat_request([{"role": "user", "content": "x"}], D), document_request("x", D, grammar="g")
    embedded = RequestShape.for_config(LLMConfig())
    assert embedded.body(chat, 1)["max_tokens"] == default_max_tokens(D) == 104
    assert embedded.body(document, 1)["max_tokens"] == DOCUMENT_BUDGET == 104
    remote = RequestShape.for_config(LLMConfig(base_url="http://h/v1", model="m"))
    assert remote.body(chat, 1)["max_tokens"] == CHAT_BUDGET == 104 + 512
    assert remote.body(document, 1)["max_tokens"] == DOCUMENT_BUDGET


def test_the_document_budget_holds_every_index_label() -> None:
    # a Humanoid-Joints continuation (D=459) was cut off after 423 values at 24 + 8 D = 3,696 tokens:
    # Gemma spends a token per character of "422:0.47,"
    assert default_max_tokens(459) == 3696 and default_max_tokens(459, labels=True) == 24 + sum(len(str(j)) + 7 for j in range(459))
    assert default_max_tokens(459, labels=True) >= len(",".join(f"{j}:-0.47" for j in range(459)) + "]")


# -- a slow CPU server against the timeout ----------------------------------------------------------------
def test_the_timeout_is_fitted_to_the_budget_from_the_measured_speed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # 1000 tokens/s of reasoning, 1 s timeout: the first answer (cut at 616 tokens) takes 0.6 s, the
    # others (1,000 tokens of reasoning and the answer) 1 s and more; the budget grows to 8,808 tokens
    r = run(tmp_path, "slow_cpu_reasoner", llm=dict(timeout_s=1.0, structured="none"))
    assert all(c["ok"] for c in r.calls), [c["error"] for c in r.calls]  # no try ran into the timeout
    assert r.calls[0]["parse_error"] == "length"
    budget, timeout_note = r.adaptations[0].split("; ")
    assert budget == f"max_tokens raised from {CHAT_BUDGET} to {CHAT_BUDGET + 8192}: the endpoint returns reasoning"
    assert timeout_note.startswith("timeout set to ") and timeout_note.endswith(
        f"s (--timeout 1): answers came at {timeout_note.split(' at ')[1].split(' ')[0]} tokens/s and up to "
        f"{CHAT_BUDGET + 8192} tokens are asked for")
    assert float(timeout_note.split()[3]) >= 2 * (CHAT_BUDGET + 8192) / 1000  # twice the budget at <= 1000 tokens/s
    assert_evaluated_the_answers(r, 2)
    assert "endpoint adapted at LLM iteration 0: max_tokens raised" in show(r.out, capsys)
    audit = audit_run(r.out)  # the audit replays the same adaptations from the recorded exchanges
    assert not audit.unverified and not audit.leaks, audit.format()


def test_a_timed_out_try_waits_twice_as_long_the_next_time(tmp_path: Path) -> None:
    with FaultServer(FaultConfig(fault_rate=0.0, personas=("slow_cpu_reasoner",))) as srv:
        conf = LLMConfig(base_url=srv.base_url, model="m", timeout_s=0.5, transport_retries=2, retry_base_s=0.01,
                         retry_max_s=0.02, max_tokens=9000, structured="none")
        client = EndpointClient(conf, base_url=srv.base_url, model="m", api_key="k", grammar_ok=False)
        ex = client.send(chat_request([{"role": "user", "content": "Answer with 10 numbers."}], D))  # 1,020 tokens: 1.02 s
        client.close()
    assert ex.ok and [f.error_kind for f in ex.failures] == ["timeout", "timeout"]
    assert [f.error.split(" within ")[1].split(" s ")[0] for f in ex.failures if f.error] == ["0.5", "1"]


def test_the_embedded_models_first_request_gets_a_timeout_fitted_to_its_budget() -> None:
    shape = RequestShape.for_config(LLMConfig())
    assert shape.timeout(document_request("x" * 1500, 10)) == 300  # CartPole: --timeout holds
    # Humanoid-Joints (D=459): a 7,933-character document; a 4,504-token answer on busy cores
    wait = shape.timeout(document_request("x" * 7933, 459))
    assert wait >= 2 * (7933 / 50 + 4504 / 5)
    remote = RequestShape.for_config(LLMConfig(base_url="http://h/v1", model="m"))
    assert remote.timeout(chat_request([{"role": "user", "content": "x" * 7933}], 459)) == 300


# -- a bullet list of too few numbers ----------------------------------------------------------------------
def test_a_bullet_list_of_too_few_numbers_is_wrong_length_and_corrected(tmp_path: Path) -> None:
    r = run(tmp_path, "bullet_list_once", llm=dict(structured="none"))
    assert r.calls[0]["content"].startswith("Here are the new parameters:\n- ")
    assert [c["parse_error"] for c in r.calls] == ["wrong_length", None, "wrong_length", None]
    correction = r.requests()[1]["messages"][-1]["content"]
    assert "expected 10 numbers, got 4" in correction
    assert_evaluated_the_answers(r, 2)


# -- llama.cpp with a template that forces thinking open ----------------------------------------------------
def test_forced_thinking_the_answer_is_read_from_reasoning_content_and_the_schema_stays(tmp_path: Path) -> None:
    r = run(tmp_path, "llamacpp_forced_think")
    assert all("response_format" in q for q in r.requests())  # sent every time; this server does not enforce it
    assert all(c["content"] == "" and c["answer_source"] == "reasoning" for c in r.calls)
    assert all(c.note == "answer taken from the reasoning text" for c in r.llm)
    assert_evaluated_the_answers(r, 2)


# -- the document form against a remote llama.cpp server ---------------------------------------------------
def test_document_form_on_a_remote_server_sends_the_grammar_and_a_stop_sequence(tmp_path: Path) -> None:
    r = run(tmp_path, "base_model_runs_on", prompt_form="document")
    for q in r.requests():
        assert q["stop"] == ["]"] and q["grammar"].startswith('root ::= "0:"')
        assert q["max_tokens"] == DOCUMENT_BUDGET and "response_format" not in q
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r, 2)


def test_document_form_without_a_grammar_the_stop_sequence_ends_the_list(tmp_path: Path) -> None:
    # the base model writes on past "]" (another entry, and another) until the token limit: 18 of 18
    # iterations were fallbacks before; the stop sequence ends it at the list
    r = run(tmp_path, "base_model_runs_on", prompt_form="document", llm=dict(structured="none"))
    assert all("grammar" not in q and q["stop"] == ["]"] for q in r.requests())
    assert all("]" not in c["content"] and json.loads(c["response"])["choices"][0]["finish_reason"] == "stop"
               for c in r.calls)
    assert not any(c["parse_error"] for c in r.calls)
    assert_evaluated_the_answers(r, 2)


def test_a_server_refusing_the_grammar_is_adapted_to_and_the_stop_sequence_serves(tmp_path: Path) -> None:
    # a completions endpoint that does not know llama.cpp's grammar: a 400 naming it, once
    r = run(tmp_path, "strict_completions", prompt_form="document")
    assert r.adaptations == ["dropped the grammar (after HTTP 400: Unrecognized request argument supplied: grammar)"]
    assert [c["ok"] for c in r.calls] == [False, True, True]
    assert "grammar" in r.requests()[0] and all("grammar" not in q and q["stop"] == ["]"] for q in r.requests()[1:])
    assert_evaluated_the_answers(r, 2)
    audit = audit_run(r.out)
    assert not audit.unverified and not audit.leaks, audit.format()


# -- the fault server's completions endpoint -----------------------------------------------------------------
def test_the_fault_server_reads_D_from_a_continuation_grammar_and_a_document() -> None:
    assert requested_dim({"prompt": "x", "grammar": continuation_grammar(7)}) == 7
    doc = "# T\n\nreturn: 1.00\nparams: [0:1.5,1:-2,2:0.3]\n\nreturn: 2.00\nparams: ["
    assert requested_dim({"prompt": doc}) == 3


# "truncated": a continuation that stops by itself before "]" reads as ended at the stop sequence "]"
# (servers do not return it), so a short one is wrong_length
@pytest.mark.parametrize("kind,error", [("empty", "empty"), ("truncated", "wrong_length"), ("wrong_length", "wrong_length"),
                                        ("nan", "non_finite"), ("prose", "no_numbers"), ("refusal", "refusal"),
                                        ("huge", None), ("several_vectors", None)])
def test_document_answer_faults_come_back_as_the_kind_they_are(kind: str, error: str | None) -> None:
    from ppprops.wire.parse import read_continuation

    with FaultServer(FaultConfig(fault_rate=1.0, kinds=(kind,), seed=3)) as srv:
        conf = LLMConfig(base_url=srv.base_url, model="m", structured="none")
        client = EndpointClient(conf, base_url=srv.base_url, model="m", api_key="k", grammar_ok=False)
        ex = client.send(document_request("# T\n\nreturn: 1.00\nparams: [0:1,1:2,2:3]\n\nreturn: 2.00\nparams: [", 3), seed=1)
        client.close()
        proposed = srv.answers()
    result = read_continuation(ex.content, 3, finish_reason=ex.finish_reason)
    assert result.error == error, (ex.content, result)
    assert (len(proposed) == 1 and list(result.values or ()) == proposed[0][2]) if error is None else proposed == []


@pytest.mark.parametrize("kind,error_kind", [("http_503", "http_503"), ("drop", "dropped"), ("bad_json", "bad_response")])
def test_transport_faults_on_the_completions_endpoint_are_retried(kind: str, error_kind: str) -> None:
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=(kind,))) as srv:
        conf = LLMConfig(base_url=srv.base_url, model="m", transport_retries=1, retry_base_s=0.01, retry_max_s=0.02)
        client = EndpointClient(conf, base_url=srv.base_url, model="m", api_key="k", grammar_ok=False)
        with pytest.raises(Exception) as info:
            client.send(document_request("return: 1.00\nparams: [0:1,1:2]\n\nreturn: 2.00\nparams: [", 2), seed=1)
        client.close()
        assert srv.stats()["requests"] == 2
    assert [t.error_kind for t in info.value.failures] == [error_kind] * 2  # type: ignore[attr-defined]
    if kind != "bad_json":  # the error names the URL tried: the completions endpoint
        assert all(f"{srv.base_url}/completions" in (t.error or "") for t in info.value.failures)  # type: ignore[attr-defined]


# -- the audit, through the real client and a real HTTP server, per request shape ---------------------------
def _plant(run_dir: Path, edit: Any) -> None:
    """Rewrite the last recorded request body with ``edit`` (a function of the parsed body)."""
    tamper_call(run_dir, [c for c in recorded_calls(run_dir) if c["ok"]][-1], request=edit)


@pytest.mark.parametrize("form", ["chat", "document"])
def test_audit_of_a_hardened_run_through_the_real_client_is_clean_and_catches_a_planted_field(tmp_path: Path, form: str) -> None:
    r = run(tmp_path, "plain", method="pp-hardened", prompt_form=form, iterations=3)
    assert len(r.llm) == 3
    # the transcript checks: what a simulator fit gets from twelve entries of a public env is its own
    # matter (tests/test_simulator_attacks.py; on this document-form run sim-marginal-lattice found c
    # within 0.64% in a CI-like check, and the audit said EXPOSED, as it should)
    report = audit_run(r.out, simulate=False)
    assert report.requests == 3 and report.exit_code(strict=True) == 0 and report.verdict().startswith("CLEAN"), report.format()
    assert not report.leaks and not report.unverified and not report.exposed

    def change_temperature(body: dict[str, Any]) -> None:
        body["temperature"] = 0.123  # not what the client sends at that call

    _plant(r.out, change_temperature)
    report = audit_run(r.out)
    assert report.exit_code() == 1 and report.verdict().startswith("UNVERIFIED")
    assert [f.detail for f in report.unverified] == ["field temperature differs from what the client sends"]


def test_audit_of_a_pp_document_run_through_the_real_client_finds_a_planted_raw_return(tmp_path: Path) -> None:
    out = tmp_path / "run"
    rng = np.random.default_rng(11)
    secrets = Secrets(run_id="doc-audit", a=rng.uniform(1.7, 4.3, D), c=3.7193)
    with FaultServer(FaultConfig(fault_rate=0.0, personas=("plain",))) as srv:
        cfg = make_config(warmup=3, iterations=3, final_episodes=0, seed=RUN_SEED, prompt_form="document",
                          llm=LLMConfig(base_url=srv.base_url, model="m", timeout_s=5.0))
        start(cfg, out, secrets=secrets)
    report = audit_run(out)
    assert report.requests == 3 and not report.leaks and not report.unverified, report.format()
    # whatever the run's own channels give (EXPOSED by the paper's scheme, or CLEAN with warnings), all by design
    assert report.verdict().startswith(("CLEAN", "EXPOSED")) and all(f.by_design for f in report.exposed), report.format()
    with open_store(out) as store:
        best = max(store.candidates()[:3], key=lambda c: c.ret)

    def leak_a_return(body: dict[str, Any]) -> None:
        shown = f"return: {best.feedback_enc.ret:.2f}\n"
        assert shown in body["prompt"]
        body["prompt"] = body["prompt"].replace(shown, f"return: {best.ret:.2f}\n", 1)

    _plant(out, leak_a_return)
    report = audit_run(out)
    assert report.exit_code() == 1 and "raw_return" in {f.kind for f in report.leaks}, report.format()


def test_audit_of_an_r2po_run_through_the_real_client_accounts_for_the_critic_request(tmp_path: Path) -> None:
    cfg_run = run(tmp_path, "plain", method="r2po", iterations=2, episodes=2)
    critic = [q for q in cfg_run.requests() if q["messages"][0]["content"].startswith("You are a critic")]
    assert len(critic) == 1 and len(cfg_run.requests()) == 2  # one search request, one critic request
    report = audit_run(cfg_run.out)
    assert not report.unverified, report.format()
    assert report.leaks and all(f.by_design for f in report.leaks)  # the critic is shown raw trajectories by design
    assert "raw_trajectory" in {f.kind for f in report.leaks}


def test_no_new_request_field_is_left_unchecked_by_the_audit() -> None:
    from ppprops.privacy.audit import SENT_FIELDS

    shape = RequestShape.for_config(LLMConfig(base_url="http://h/v1", model="m", reasoning_effort="low"))
    sent = set(shape.body(chat_request([{"role": "user", "content": "x"}], D), 1)) | set(
        shape.body(document_request("x", D, grammar="g", temperature=0.5), 1))
    assert sent <= SENT_FIELDS and "stop" in sent


def test_replay_of_the_shape_learns_the_same_timeout_from_the_recorded_exchange() -> None:
    live = RequestShape.for_config(LLMConfig(base_url="http://h/v1", model="m", timeout_s=10.0))
    req = chat_request([{"role": "user", "content": "x" * 10}], D)
    live.body(req, 1)
    notes = live.learn(req, '{"params": [1,2,3,4,5,6,7,8,9,10]}', None, latency_s=30.0, completion_tokens=300)
    # twice the budget at 10 tokens/s is 123.2 s, rounded up to whole 10 s
    assert notes == [f"timeout set to 130 s (--timeout 10): answers came at 10.0 tokens/s and up to {CHAT_BUDGET} "
                     "tokens are asked for"] and live.timeout(req) == 130
    quick = replace(live.config, timeout_s=1000.0)
    assert RequestShape(quick, model="m", grammar_ok=False).learn(req, "x", None, latency_s=3.0, completion_tokens=3) == []
