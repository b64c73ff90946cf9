"""The audit accounts exactly for what the client sends: correction turns (one user
message, or prompt + the provider's own final text + correction), and request fields the client
adapted to its endpoint (a dropped seed, temperature or schema, max_completion_tokens, a token
budget raised for reasoning), session by session across a resume. A value planted in any of these
places still fails it.

Runs are real CartPole searches against the fault server answering as every persona, with transport
faults; the run seed is large, so the one implementation channel the audit scores besides the
paper's (replaying a small run seed) does not apply. (A schema dropped and restored is replayed in
tests/unit/test_adaptations_on_evidence.py.)
"""

from __future__ import annotations

import json
import shutil
import sqlite3
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig, RunConfig
from ppprops.privacy import reconstruct
from ppprops.privacy.audit import AuditReport, audit_run
from ppprops.privacy.reconstruct import ClientReplay
from ppprops.runner import RunEvents, resume, start
from ppprops.store import Candidate, open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer
from ppprops.testing.personas import PERSONAS
from ppprops.wire.forms import CHAT
from ppprops.wire.parse import final_text
from ppprops.wire.prompt import build_correction
from ppprops.wire.turns import ECHO_CHARS, REPEATS_HISTORY, correction_messages

from support import make_config, recorded_calls, tamper_call

D = 10  # CartPole
RUN_SEED = 913_572_448
SERVER_SEED = 7  # a fault and persona sequence under which 30 iterations reach every form below (asserted)


def _secrets() -> Secrets:
    rng = np.random.default_rng(11)
    return Secrets(run_id="corrections", a=rng.uniform(1.7, 4.3, D), c=3.7193)


def _llm(server: FaultServer) -> LLMConfig:
    # temperature 0.7: OpenAI's reasoning models refuse any but 1, so the client drops it
    return LLMConfig(base_url=server.base_url, model="m", temperature=0.7, timeout_s=5.0, retry_base_s=0.01, retry_max_s=0.02)


def _server(personas: tuple[str, ...], fault_rate: float, seed: int) -> FaultServer:
    return FaultServer(FaultConfig(fault_rate=fault_rate, personas=personas, seed=seed, timeout_s=0.2, delay_max_s=0.05,
                                   retry_after_s=0.05))


def _calls(run: Path) -> list[dict[str, Any]]:
    store = open_store(run)
    try:
        return store.llm_calls()
    finally:
        store.close()


def _adaptations(run: Path) -> list[str]:
    store = open_store(run)
    try:
        return [a["change"] for a in store.llm_adaptations()]
    finally:
        store.close()


def assert_accounted_for(r: AuditReport) -> None:
    """No raw value sent, nothing unaccounted for, and any exposure is a channel of the paper's scheme
    (or a simulator fit of the public env, which no encoding closes)."""
    assert not r.leaks and not r.unverified, r.format()
    assert all(f.by_design or f.kind.startswith("sim-") for f in r.exposed), r.format()
    assert r.verdict().startswith(("CLEAN", "EXPOSED")), r.verdict()


@pytest.fixture(scope="module")
def persona_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("personas") / "run"
    with _server(tuple(PERSONAS), 0.3, SERVER_SEED) as srv:
        start(make_config(warmup=5, iterations=30, final_episodes=0, seed=RUN_SEED, llm=_llm(srv)), out, secrets=_secrets())
    return out


def _forms(run: Path) -> set[str]:
    """Which request forms and adaptations a run's transcript holds."""
    calls = _calls(run)
    found = set()
    answers = {(c["iteration"], c["attempt"]): c for c in calls if c["ok"]}
    for c in calls:
        messages = json.loads(c["request"])["messages"]
        if c["attempt"] >= 1 and len(messages) == 1:
            found.add("correction in the prompt's message")
        if len(messages) == 3:
            found.add("echoed final text")
            previous = answers[(c["iteration"], c["attempt"] - 1)]
            if messages[1]["content"] != (previous["content"] or "").strip():
                found.add("echo without the answer's reasoning or markup")
        if c["parse_error"] == "repeats_history":
            found.add("repeated history entry")
    for change in _adaptations(run):
        for what in ("raised", "dropped seed", "dropped temperature", "instead of max_tokens", "dropped the JSON schema"):
            if what in change:
                found.add(what)
    return found


EVERY_FORM = {"correction in the prompt's message", "echoed final text", "echo without the answer's reasoning or markup",
              "repeated history entry", "raised", "dropped seed", "dropped temperature", "instead of max_tokens",
              "dropped the JSON schema"}


def test_a_run_against_every_persona_with_faults_sends_nothing_the_audit_cannot_account_for(persona_run: Path) -> None:
    assert _forms(persona_run) == EVERY_FORM  # the run reached every correction form and every adaptation
    r = audit_run(persona_run)
    assert_accounted_for(r)
    assert r.requests == len(_calls(persona_run)) and r.entries > 0


def test_the_audit_replays_the_clients_adaptations_exactly(persona_run: Path) -> None:
    store = open_store(persona_run)
    try:
        config = RunConfig.from_json(store.config())
        task = config.make_task()
        ctx = reconstruct.context(task, config, reconstruct.client_codec(task, config, None), CHAT)
        replay = ClientReplay(config.llm, D, store.llm_sessions(), store.endpoint_changes())
        calls, recorded = store.llm_calls(), [a["change"] for a in store.llm_adaptations()]
    finally:
        store.close()
    for row in calls:
        req = CHAT.request("", ctx=ctx, shown=[], iteration=row["iteration"], attempt=row["attempt"], temperature=config.llm.temperature)
        expected = replay.fields(req)
        sent = json.loads(row["request"])
        assert set(sent) - {"messages"} == set(expected), row["id"]
        assert {k: v for k, v in sent.items() if k not in ("messages", "seed")} == \
            {k: v for k, v in expected.items() if k != "seed"}, row["id"]
        replay.observe(row, req)
    assert replay.changes == recorded and len(recorded) == 5


# -- planted values ---------------------------------------------------------------------------------
def _raw_return(run: Path) -> int:
    """A raw integer return of a candidate the run showed, far from its encoded value."""
    store = open_store(run)
    cands: list[Candidate] = store.candidates()
    store.close()
    return next(int(c.ret) for c in cands if c.ret >= 20 and float(c.ret).is_integer())


def _one_message_correction(call: dict[str, Any]) -> bool:
    return call["attempt"] >= 1 and len(call["body"]["messages"]) == 1


def _echo(call: dict[str, Any]) -> bool:
    return len(call["body"]["messages"]) == 3


def _in_correction(doc: dict[str, Any], i: int, text: str) -> None:
    head = "That answer could not be used: "
    assert head in doc["messages"][i]["content"]
    doc["messages"][i]["content"] = doc["messages"][i]["content"].replace(head, f"That answer could not be used {text}: ", 1)


PLANTS: dict[str, tuple[Callable[[dict[str, Any]], bool], Callable[[dict[str, Any], int], None]]] = {
    "the one-message correction": (_one_message_correction, lambda d, r: _in_correction(d, 0, f"(the best return is {r})")),
    "the echoed assistant turn": (_echo, lambda d, r: d["messages"][1].update(
        content=d["messages"][1]["content"] + f" The best return so far is {r}.")),
    "the echoed assistant turn, replaced": (_echo, lambda d, r: d["messages"][1].update(content=f"My return was {r}.")),
    "the correction turn": (_echo, lambda d, r: _in_correction(d, 2, f"(the best return is {r})")),
    "the adapted token field": (lambda c: "max_completion_tokens" in c["body"], lambda d, r: d.update(max_completion_tokens=r)),
    "the renamed token field sent again": (lambda c: "max_completion_tokens" in c["body"], lambda d, r: d.update(max_tokens=r)),
    "the dropped seed sent again": (lambda c: "seed" not in c["body"], lambda d, r: d.update(seed=r)),
    "the dropped temperature sent again": (lambda c: "temperature" not in c["body"], lambda d, r: d.update(temperature=r)),
}


@pytest.mark.parametrize("where", list(PLANTS))
def test_a_raw_value_planted_where_the_client_adapts_or_corrects_fails_the_audit(persona_run: Path, tmp_path: Path,
                                                                                where: str) -> None:
    run = tmp_path / "run"
    shutil.copytree(persona_run, run)
    raw = _raw_return(run)
    pick, plant = PLANTS[where]
    call_id = tamper_call(run, pick, request=lambda d: plant(d, raw))  # the first recorded request pick selects
    r = audit_run(run)
    assert r.exit_code() == 1 and "raw_return" in {f.kind for f in r.leaks}, r.format()
    assert all(f"call {call_id} " in loc for f in r.leaks for loc in f.locations), r.format()


def test_a_correction_that_names_another_fault_is_unverified(persona_run: Path, tmp_path: Path) -> None:
    """The fault a correction names is re-derived from the recorded answer, not merely a template match."""
    run = tmp_path / "run"
    shutil.copytree(persona_run, run)
    calls = {c["id"]: c for c in _calls(run)}

    def swap(doc: dict[str, Any]) -> None:
        text = doc["messages"][0]["content"]
        tail = text[text.rindex("\n\nThat answer could not be used: "):]
        other = "the answer was empty" if "the answer was empty" not in tail else "the answer declined to propose parameters"
        doc["messages"][0]["content"] = text[: -len(tail)] + "\n\n" + build_correction(other, D)

    call_id = tamper_call(run, _one_message_correction, request=swap)
    r = audit_run(run)
    assert not r.leaks and r.exit_code() == 1, r.format()
    assert r.unverified and all(f"call {call_id} " in loc for f in r.unverified for loc in f.locations), r.format()
    assert calls[call_id]["attempt"] >= 1


def test_a_correction_after_an_answer_the_client_would_take_is_unverified(persona_run: Path, tmp_path: Path) -> None:
    """A 'repeats the history' correction is accounted for only if the answer did repeat a shown policy."""
    run = tmp_path / "run"
    shutil.copytree(persona_run, run)
    rows = recorded_calls(run)
    refused = next(r for r in rows if r["content"] and r["content"] == final_text(r["content"]) and
                   r["parse_error"] == "repeats_history")
    new = json.dumps({"params": [0.123] * D})  # a policy that is in no history
    tamper_call(run, refused, content=new)
    after = [r for r in rows if r["id"] > refused["id"] and r["iteration"] == refused["iteration"] and
             r["attempt"] == refused["attempt"] + 1]  # every try of the correction

    def echo_new(doc: dict[str, Any]) -> None:
        assert doc["messages"][1]["content"] == refused["content"].strip()
        doc["messages"][1]["content"] = new  # the echo stays the answer's own text

    for call in after:
        tamper_call(run, call, request=echo_new)
    r = audit_run(run)
    assert not r.leaks, r.format()
    assert [(f.detail, f.locations) for f in r.unverified] == [
        ("a correction after an answer the client takes (it repeats no policy of the history shown)",
         [f"call {a['id']} (iteration {a['iteration']}, attempt {a['attempt']})" for a in after])], r.format()


# -- a resumed run --------------------------------------------------------------------------------------
ADAPTING = ("gemini_openai", "openai_reasoning", "deepseek_reasoner", "vllm_gpt_oss", "repeats_history_once", "harmony_markup")


def _interrupted_and_resumed(out: Path) -> None:
    def stop_after_four_llm_candidates(c: Candidate, latency: float | None, best: float) -> None:
        if c.source != "warmup" and c.iteration == 3:
            raise KeyboardInterrupt

    with _server(ADAPTING, 0.2, 1) as srv:
        cfg = make_config(warmup=5, iterations=8, final_episodes=0, seed=RUN_SEED, llm=_llm(srv))
        with pytest.raises(KeyboardInterrupt):
            start(cfg, out, RunEvents(on_candidate=stop_after_four_llm_candidates), secrets=_secrets())
        resume(out)


@pytest.fixture(scope="module")
def resumed_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("resumed") / "run"
    _interrupted_and_resumed(out)
    return out


def test_a_resumed_run_whose_client_adapts_again_audits_the_same(resumed_run: Path) -> None:
    store = open_store(resumed_run)
    sessions, candidates, adaptations = store.llm_sessions(), store.candidates(), store.llm_adaptations()
    store.close()
    assert len(candidates) == 13 and sessions is not None and len(sessions) == 2 and sessions[0] == 0
    before = [a["change"].split(" (")[0] for a in adaptations if a["iteration"] <= 3]
    again = [a["change"].split(" (")[0] for a in adaptations if a["iteration"] >= 4]
    assert "dropped seed" in before and "dropped seed" in again  # the fresh client of the resume adapted anew
    assert_accounted_for(audit_run(resumed_run))


def test_without_its_session_record_the_resumed_clients_requests_are_not_accounted_for(resumed_run: Path, tmp_path: Path) -> None:
    """The replay is exact, not permissive: one client throughout cannot have sent the seed it dropped."""
    run = tmp_path / "run"
    shutil.copytree(resumed_run, run)
    db = sqlite3.connect(run / "run.sqlite")
    db.execute("DELETE FROM meta WHERE key = 'llm_sessions'")
    db.commit()
    db.close()
    r = audit_run(run)
    assert r.exit_code() == 1 and any("does not send at this point" in f.detail for f in r.unverified), r.format()


# -- the rule both sides use ------------------------------------------------------------------------------
def test_correction_messages_echo_only_final_text_and_fold_into_the_prompt_without_it() -> None:
    harmony = '<|channel|>analysis<|message|>best is [1,2]<|end|><|start|>assistant<|channel|>final<|message|>{"params": [1]}'
    assert correction_messages("P", harmony, "why", 2) == [
        {"role": "user", "content": "P"}, {"role": "assistant", "content": '{"params": [1]}'},
        {"role": "user", "content": build_correction("why", 2)}]
    for nothing in (None, "", "<think>only reasoning</think>"):
        assert correction_messages("P", nothing, REPEATS_HISTORY, 2) == [
            {"role": "user", "content": "P\n\n" + build_correction(REPEATS_HISTORY, 2)}]
    long = "x" * (ECHO_CHARS + 50)
    assert correction_messages("P", long, "why", 2)[1]["content"] == "x" * ECHO_CHARS
