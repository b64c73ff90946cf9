"""Prompt forms own their request end to end (``ppprops.wire.forms``): what each form asks for, how
the transport turns it into a body (``RequestShape.body``), how its answers and recorded prompts are
read back, and what its recorded decisions may be. No model, no HTTP."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from ppprops.llm.client import EXPLANATION_ROOM, RequestShape
from ppprops.llm.settings import LLMConfig
from ppprops.wire import EncodedEntry, PromptContext
from ppprops.wire.document import EXPLORE_SAMPLING, EXPLORE_TEMPERATURE, STALL_AFTER, TEMPERATURES, document_target
from ppprops.wire.forms import (
    CHAT,
    CHAT_TEMPERATURE,
    CRITIC,
    DOCUMENT,
    ENDPOINT_CHAT,
    ENDPOINT_COMPLETIONS,
    FORMS,
    REPEAT_PENALTY,
    answer_budget,
    params_grammar,
    params_schema,
    recorded_form,
)
from ppprops.wire.prompt import template
from ppprops.wire.turns import REPEATS_HISTORY

CTX = PromptContext(summary="s", observations=(("x", "position"), ("v", "speed")), actions=("left", "right"), discrete=True,
                    reward_text="r", hints="", encoded_params=True, scaled_rewards=True, detailed_feedback=True,
                    param_range=None, optimum=None, title="T")
SHOWN = [EncodedEntry(0, (1.0, -2.0, 0.5, 3.0, -1.0, 0.25), 10.0), EncodedEntry(1, (1.5, -2.5, 0.5, 3.0, -1.0, 0.25), 20.0)]
EMBEDDED = LLMConfig()
REMOTE = LLMConfig(base_url="http://h/v1", model="m")


def test_the_forms_are_registered_by_name_and_the_choosable_ones_are_chat_and_document() -> None:
    assert FORMS == {"chat": CHAT, "document": DOCUMENT, "r2po-critic": CRITIC}
    assert (CHAT.endpoint, DOCUMENT.endpoint, CRITIC.endpoint) == (ENDPOINT_CHAT, ENDPOINT_COMPLETIONS, ENDPOINT_CHAT)


def test_the_chat_form_asks_for_its_json_object_at_its_temperature() -> None:
    req = CHAT.request("PROMPT", ctx=CTX, shown=SHOWN, iteration=3, attempt=0)
    assert req.messages == ({"role": "user", "content": "PROMPT"},) and req.prompt is None
    assert (req.form, req.endpoint, req.D, req.iteration, req.attempt) == ("chat", ENDPOINT_CHAT, 6, 3, 0)
    assert dict(req.sampling) == {"temperature": CHAT_TEMPERATURE} and req.decisions == {}
    assert req.json_schema == params_schema(6) and req.grammar == params_grammar(6) and req.stop == ()
    assert req.answer_tokens == answer_budget(6) == 24 + 8 * 6 and req.explains
    assert CHAT.request("P", ctx=CTX, shown=SHOWN, iteration=0, attempt=0, temperature=0.3).sampling == {"temperature": 0.3}


def test_a_chat_retry_is_the_correction_turns_and_records_the_fault() -> None:
    req = CHAT.request("PROMPT", ctx=CTX, shown=SHOWN, iteration=0, attempt=1, previous='{"params": [1]}', detail="expected 6 numbers")
    assert [m["role"] for m in req.messages or ()] == ["user", "assistant", "user"]
    assert req.messages is not None and req.messages[1]["content"] == '{"params": [1]}'
    assert req.decisions == {"correction": "expected 6 numbers"}


def test_the_document_form_asks_for_a_continuation_on_its_schedule() -> None:
    req = DOCUMENT.request("DOC", ctx=CTX, shown=SHOWN, iteration=1, attempt=0)
    assert req.prompt == "DOC" and req.messages is None and req.endpoint == ENDPOINT_COMPLETIONS
    assert dict(req.sampling) == {"temperature": TEMPERATURES[1]}
    assert req.json_schema is None and req.grammar is not None and req.grammar.startswith('root ::= "0:"') and req.stop == ("]",)
    assert req.answer_tokens == answer_budget(6, labels=True) and not req.explains
    assert req.decisions == {"temperature": TEMPERATURES[1], "target": document_target(SHOWN), "stalled": 0}
    stuck = DOCUMENT.request("DOC", ctx=CTX, shown=SHOWN, iteration=1, attempt=0, stalled=STALL_AFTER)
    assert dict(stuck.sampling) == {"temperature": EXPLORE_TEMPERATURE, **EXPLORE_SAMPLING} and stuck.decisions["stalled"] == STALL_AFTER


def test_a_document_retry_after_a_copied_entry_penalises_repeats_and_is_sent_as_it_is() -> None:
    first = DOCUMENT.request("DOC", ctx=CTX, shown=SHOWN, iteration=2, attempt=0)
    copied = DOCUMENT.request("DOC", ctx=CTX, shown=SHOWN, iteration=2, attempt=1, previous="0:1.5]", detail=REPEATS_HISTORY)
    cut = DOCUMENT.request("DOC", ctx=CTX, shown=SHOWN, iteration=2, attempt=1, previous="0:1.", detail="cut off")
    assert "repeat_penalty" not in first.sampling and "repeat_penalty" not in cut.sampling
    assert copied.sampling["repeat_penalty"] == REPEAT_PENALTY
    assert RequestShape.for_config(EMBEDDED).body(copied, 1)["repeat_penalty"] == REPEAT_PENALTY


@pytest.mark.parametrize("llm,chat_fields,document_fields", [
    (EMBEDDED, {"model", "messages", "temperature", "max_tokens", "seed", "grammar"},
     {"model", "prompt", "temperature", "max_tokens", "seed", "grammar"}),
    (REMOTE, {"model", "messages", "temperature", "max_tokens", "seed", "response_format"},
     {"model", "prompt", "temperature", "max_tokens", "seed", "grammar", "stop"}),
])
def test_the_transport_adds_the_endpoints_fields_to_each_forms_request(llm: LLMConfig, chat_fields: set[str],
                                                                       document_fields: set[str]) -> None:
    shape = RequestShape.for_config(llm)
    chat = shape.body(CHAT.request("P", ctx=CTX, shown=SHOWN, iteration=0, attempt=0), 7)
    doc = shape.body(DOCUMENT.request("D", ctx=CTX, shown=SHOWN, iteration=0, attempt=0), 7)
    assert set(chat) == chat_fields and set(doc) == document_fields and chat["seed"] == doc["seed"] == 7
    explain = EXPLANATION_ROOM if not llm.embedded else 0
    assert chat["max_tokens"] == answer_budget(6) + explain and doc["max_tokens"] == answer_budget(6, labels=True)
    json.dumps(chat), json.dumps(doc)  # plain JSON, as sent


def test_a_sampling_field_the_endpoint_refuses_is_dropped_by_its_own_name() -> None:
    from ppprops.llm.client import ServerError

    shape = RequestShape.for_config(REMOTE)
    stuck = DOCUMENT.request("D", ctx=CTX, shown=SHOWN, iteration=0, attempt=0, stalled=STALL_AFTER)
    assert "min_p" in shape.body(stuck, 1)
    change, _ = shape.adapt(ServerError(400, "Unrecognized request argument supplied: min_p"))
    assert change is not None and change.startswith("dropped min_p") and "min_p" not in shape.body(stuck, 1)


def test_each_form_reads_its_own_answers_and_refuses_a_repeat_of_the_history() -> None:
    assert CHAT.read('{"params": [1, 2, 3, 4, 5, 6]}', 6).values == (1, 2, 3, 4, 5, 6)
    assert DOCUMENT.read("0:1,1:2,2:3,3:4,4:5,5:6]", 6).values == (1, 2, 3, 4, 5, 6)
    repeat = DOCUMENT.judge("0:1.5,1:-2.5,2:0.5,3:3,4:-1,5:0.25]", None, CTX, SHOWN)
    assert repeat.error == "repeats_history" and repeat.detail == REPEATS_HISTORY


def test_each_form_reads_back_the_entries_it_printed_and_names_the_number_it_derives() -> None:
    for form in (CHAT, DOCUMENT):
        text = form.prompt(CTX, SHOWN)
        entries = form.entries(text)
        assert [e.ret for e in entries] == ["10.00", "20.00"], form.name
        assert [text[e.start:e.end] for e in entries] == [form.render_entry(CTX, e) for e in SHOWN], form.name
    assert CHAT.derived(CHAT.prompt(CTX, SHOWN), SHOWN) == []
    (target,) = DOCUMENT.derived(DOCUMENT.prompt(CTX, SHOWN), SHOWN)
    assert target.kind == "target" and target.value == document_target(SHOWN) and float(target.token) == pytest.approx(target.value, abs=0.01)


def test_a_decision_the_form_did_not_make_is_named() -> None:
    ok = DOCUMENT.request("D", ctx=CTX, shown=SHOWN, iteration=2, attempt=1).decisions
    assert DOCUMENT.check_decisions(ok, CTX, SHOWN, iteration=2, attempt=1, temperature=None) == []
    forged = {**ok, "stalled": 7, "note": "x"}
    assert DOCUMENT.check_decisions(forged, CTX, SHOWN, iteration=2, attempt=1, temperature=None) == [
        "unknown decision 'note'", "stall count 7 is not the 0 the shown returns give"]
    assert CHAT.check_decisions({"correction": "x", "temperature": 2}, CTX, SHOWN, iteration=0, attempt=1, temperature=None) == [
        "unknown decision 'temperature'"]


@pytest.mark.parametrize("body,form", [
    ('{"model": "m", "prompt": "return: 1\\nparams: ["}', "document"),
    ('{"model": "m", "messages": [{"role": "user", "content": "You are a good global RL policy optimizer"}]}', "chat"),
    (json.dumps({"model": "m", "messages": [{"role": "user", "content": template("r2po_critic").template.split("$")[0] + "the task"}]}),
     "r2po-critic"),
    ("not json", "chat"),
])
def test_a_call_recorded_before_calls_named_their_form_gets_the_one_its_body_shows(body: str, form: str) -> None:
    assert recorded_form(body) == form


def test_a_run_whose_retries_carry_the_repeat_penalty_is_accounted_for_by_the_audit(tmp_path: Path) -> None:
    import numpy as np

    from ppprops.client.secrets import Secrets
    from ppprops.privacy.audit import audit_run
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.runner import start

    from support import make_config, recorded_calls

    class Copycat(EchoOptimizer):
        """Continues the document with its best entry on a first attempt, a new policy on a retry."""

        def send(self, request, *, seed=None):  # type: ignore[no-untyped-def]
            ex = super().send(request, seed=seed)
            if request.attempt == 0:
                best = DOCUMENT.entries(request.prompt)[-1]
                ex = replace(ex, content=",".join(f"{i}:{v}" for i, v in enumerate(best.params)) + "]")
            return ex

    config = make_config("CartPole", "pp", warmup=3, iterations=2, final_episodes=0, prompt_form="document")
    # fixed secrets, so the run (and the stand-in's answers, which depend on them) is the same every time
    start(config, tmp_path / "r", llm=Copycat(config.llm), secrets=Secrets.generate("copycat", 10, rng=np.random.default_rng(0)))
    calls = recorded_calls(tmp_path / "r")
    assert [(c["attempt"], c["parse_error"], c["body"].get("repeat_penalty")) for c in calls] == [
        (0, "repeats_history", None), (1, None, REPEAT_PENALTY)] * 2
    report = audit_run(tmp_path / "r", attacks=False)
    assert not report.unverified and not report.leaks, report.format()
