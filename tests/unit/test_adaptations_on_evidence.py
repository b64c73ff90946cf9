"""Adaptations a flaky endpoint must not fool: each is a hypothesis about the server, made on what
the server itself did, checked afterwards, and reverted (and said so) when the answers after it are
no better. Real CartPole searches against the fault server (in this process: a thread), with a
burst of bad answers at a chosen moment; the audit replays every change from the recording.

- A burst of garbage under the JSON schema (answers that are not JSON) may drop the schema, but a
  model that needs it answers no better without it, and the schema comes back.
- A burst of answers cut short (a truncated list: a JSON object begun) is no evidence that the
  server ignores the schema: it is never dropped.
- An answer cut off after 10 tokens, far from the budget and from any context size, is a truncated
  answer, with no advice about the server's context or the token budget.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig, RunConfig
from ppprops.llm.client import SCHEMA_MISSES, SCHEMA_TRIAL, RequestShape, context_full
from ppprops.privacy import reconstruct
from ppprops.privacy.audit import audit_run
from ppprops.privacy.reconstruct import ClientReplay
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer
from ppprops.wire.forms import CHAT

from support import chat_request, make_config

D = 10  # CartPole


def _run(tmp_path: Path, config: FaultConfig, iterations: int = 4) -> tuple[Path, list[dict[str, Any]], list[str]]:
    out = tmp_path / "run"
    with FaultServer(config) as srv:
        llm = LLMConfig(base_url=srv.base_url, model="m", timeout_s=5.0, transport_retries=1, retry_base_s=0.01, retry_max_s=0.02)
        start(make_config(warmup=3, iterations=iterations, final_episodes=0, seed=913_572_448, llm=llm), out,
              secrets=Secrets(run_id="evidence", a=np.full(D, 2.0), c=1.0))
    with open_store(out) as store:
        return out, store.llm_calls(), [a["change"] for a in store.llm_adaptations()]


def _schema_sent(calls: list[dict[str, Any]]) -> list[bool]:
    return ["response_format" in json.loads(c["request"]) for c in calls]


def _replayed_clean(out: Path) -> None:
    """The audit rebuilds every request, the adapted and restored fields included: nothing unaccounted
    for; and its replay of the client (``ClientReplay``) makes exactly the changes the client recorded."""
    report = audit_run(out, attacks=False)
    assert not report.leaks and not report.unverified and report.requests > 0, report.format()
    with open_store(out) as store:
        config = RunConfig.from_json(store.config())
        task = config.make_task()
        ctx = reconstruct.context(task, config, reconstruct.client_codec(task, config, None), CHAT)
        replay = ClientReplay(config.llm, D, store.llm_sessions(), store.endpoint_changes())
        calls, recorded = store.llm_calls(), [a["change"] for a in store.llm_adaptations()]
    for row in calls:
        req = CHAT.request("", ctx=ctx, shown=[], iteration=row["iteration"], attempt=row["attempt"], temperature=config.llm.temperature)
        expected = {k: v for k, v in replay.fields(req).items() if k != "seed"}
        assert {k: v for k, v in json.loads(row["request"]).items() if k not in ("messages", "seed")} == expected, row["id"]
        replay.observe(row, req)
    assert replay.changes == recorded


DROPPED = (f"dropped the JSON schema (plain answers): {SCHEMA_MISSES} answers in a row under it were unusable and not JSON, as "
           "from a server that ignores it; it comes back if the answers without it are no better")


def test_a_burst_of_garbage_under_the_schema_does_not_lose_it_for_a_model_that_needs_it(tmp_path: Path,
                                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    # requests 1 and 2 (the first LLM iteration's answer and its first correction): prose and a refusal, injected;
    # every other answer is the needs_schema persona's: the object under the schema, prose without it
    config = FaultConfig(fault_rate=0.0, kinds=("prose", "refusal"), personas=("needs_schema",), burst=(1, 2), seed=1)
    out, calls, changes = _run(tmp_path, config)
    restored = f"restored the JSON schema: 0 of {SCHEMA_TRIAL} answers without it were usable, against 0 of 2 with it; it stays"
    assert changes == [DROPPED, restored]
    # under the schema twice (garbage), then without it 3 times (prose), then under it for good
    assert _schema_sent(calls) == [True, True] + [False] * SCHEMA_TRIAL + [True] * (len(calls) - 2 - SCHEMA_TRIAL)
    with open_store(out) as store:
        sources = [c.source for c in store.candidates()]
    assert sources == ["warmup"] * 3 + ["fallback", "llm", "llm", "llm"]  # iteration 2's third attempt is usable again
    _replayed_clean(out)
    assert main(["show", str(out)]) == 0
    shown = capsys.readouterr().out.splitlines()
    assert [x for x in shown if x.startswith("endpoint adapted")] == [f"endpoint adapted at LLM iteration 0: {DROPPED}",
                                                                       f"endpoint adapted at LLM iteration 1: {restored}"]


def test_a_burst_of_answers_cut_short_under_the_schema_keeps_it(tmp_path: Path) -> None:
    # a truncated list is a JSON object begun: the server held to the schema, the answer was cut on its way
    config = FaultConfig(fault_rate=0.0, kinds=("truncated",), personas=("needs_schema",), burst=(1, 3), seed=1)
    out, calls, changes = _run(tmp_path, config)
    assert changes == [] and all(_schema_sent(calls))
    assert [c["parse_error"] for c in calls[:4]] == ["truncated", "truncated", "truncated", None]
    _replayed_clean(out)


def test_an_answer_cut_short_far_from_any_limit_gets_no_context_advice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, calls, changes = _run(tmp_path, FaultConfig(fault_rate=0.0, personas=("cut_short",)), iterations=2)
    assert [c["parse_error"] for c in calls] == ["truncated"] * 6 and [c["completion_tokens"] for c in calls] == [10] * 6
    assert main(["show", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "context" not in shown and "--max-tokens" not in shown
    assert "answers  unusable: truncated x6" in shown.splitlines()
    assert "fallback truncated x2" in shown.splitlines()


# -- the rules, call by call -------------------------------------------------------------------------------------
def test_a_full_context_is_judged_on_the_usage_alone() -> None:
    assert context_full(616, 4076, 20)  # a usual context size (4096) reached below the budget
    assert not context_full(616, 1500, 10)  # cut below the budget, nowhere near a context size: no evidence
    assert not context_full(616, 100, 616)  # the budget stopped it
    assert context_full(None, 16300, 84, context_size=16384) and not context_full(616, 1500, 10, context_size=16384)
    shape = RequestShape(LLMConfig(base_url="http://x/v1", model="m"), model="m", grammar_ok=False)
    assert not shape.context_full(616, 2990, 10)  # a ceiling of 3000 seen once
    assert not shape.context_full(616, 2990, 10)  # the same request again: the same prompt, no new evidence
    assert shape.context_full(616, 2996, 4)  # another prompt stopped at the same ceiling: the context is full


def test_the_schema_is_dropped_only_on_answers_that_ignore_it_and_restored_when_no_better() -> None:
    shape = RequestShape(LLMConfig(base_url="http://x/v1", model="m"), model="m", grammar_ok=False)
    req = chat_request([{"role": "user", "content": "propose"}], D)
    good = json.dumps({"params": [0.5] * D})
    for content in ('{"params": [0.5, 0.1', '{"params": [0.5]}', "prose", '{"params": [1, 2'):
        assert shape.learn(req, content, None, finish_reason="stop") == []  # JSON begun, or a single miss
    assert shape.structured == "json_schema"
    assert shape.learn(req, "", None, finish_reason="stop") == [] and shape.learn(req, "no", None, finish_reason="stop") == [DROPPED]
    assert shape.structured == "none" and "response_format" not in shape.body(req, None)
    assert shape.learn(req, good, None, finish_reason="stop") == []
    assert shape.learn(req, "prose", None, finish_reason="stop") == []
    # 1 of 3 usable without it, against 0 of 6 with it: better, it stays dropped; still checked at every answer
    assert shape.learn(req, "prose", None, finish_reason="stop") == []
    assert shape.learn(req, "prose", None, finish_reason="stop") == []  # 1 of 4 is still better than 0 of 6
    assert shape.structured == "none"


def test_a_model_that_does_better_without_the_schema_keeps_it_dropped() -> None:
    shape = RequestShape(LLMConfig(base_url="http://x/v1", model="m"), model="m", grammar_ok=False)
    req = chat_request([{"role": "user", "content": "propose"}], D)
    junk = 'The user says "\n\n    \t}\n'  # Ollama's gpt-oss under a JSON schema
    assert shape.learn(req, junk, None) == [] and shape.learn(req, junk, None) == [DROPPED]
    good = json.dumps({"params": [0.5] * D})
    assert [shape.learn(req, good, None) for _ in range(5)] == [[]] * 5 and shape.structured == "none"
