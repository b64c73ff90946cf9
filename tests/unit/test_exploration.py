"""The document form explores when the search is stuck: after STALL_AFTER LLM iterations
in a row that did not raise the best shown return, an iteration is sampled at EXPLORE_TEMPERATURE.
The decision is recorded with the call, made from public values only, and the audit recomputes it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ppprops.client.secrets import Secrets
from ppprops.llm.client import RequestShape
from ppprops.llm.protocol import Exchange
from ppprops.privacy.audit import audit_run
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.wire.document import EXPLORE_SAMPLING, EXPLORE_TEMPERATURE, STALL_AFTER, TEMPERATURES

from support import make_config, tamper_call


class Stubborn:
    """A base model that always continues the document with the same poor policy."""

    def __init__(self, llm: Any) -> None:
        self.shape = RequestShape.for_config(llm)  # the body the run's own client would send
        self.temperatures: list[float] = []
        self.sampling: list[dict[str, float]] = []

    endpoints = ("completions",)

    def send(self, request: Any, *, seed: int | None = None) -> Exchange:
        assert request.endpoint == "completions", "the document form never chats"
        sampling = dict(request.sampling)
        self.temperatures.append(float(sampling.pop("temperature", 0.0)))
        self.sampling.append(sampling)
        body = self.shape.body(request, seed)
        content = ",".join(f"{i}:{0.01 * len(self.temperatures) - 0.5:.2f}" for i in range(request.D)) + "]"  # new each time
        return Exchange.answer(request, content, body=json.dumps(body))

    def close(self) -> None:
        pass


def _run(tmp_path: Path, explore: bool = True) -> tuple[Path, Stubborn]:
    # the decimal format: the stubborn model's answers (-0.49, -0.48, ...) are new each time at two decimals
    config = replace(make_config("CartPole", "pp", warmup=3, iterations=8, final_episodes=0, seed=2, number_format="decimal"),
                     prompt_form="document", select_top=0, explore=explore)
    chat = Stubborn(config.llm)
    # fixed secrets: with some fresh ones the stubborn answers keep raising the best return and the search never stalls
    start(config, tmp_path / "r", llm=chat, secrets=Secrets.generate("stuck", 10, rng=np.random.default_rng(1)))  # CartPole: D = 10
    return tmp_path / "r", chat


def test_a_stuck_search_is_sampled_hotter_and_the_choice_is_recorded(tmp_path: Path) -> None:
    run, chat = _run(tmp_path)
    with open_store(run) as store:
        cands, calls = store.candidates(), store.llm_calls()
    stalled = []
    best, k = max(c.feedback_enc.ret for c in cands[:3]), 0
    for c in cands[3:]:  # the count as the proposer keeps it, from the returns shown
        stalled.append(k)
        k = 0 if c.feedback_enc.ret > best else k + 1
        best = max(best, c.feedback_enc.ret)
    expected = [EXPLORE_TEMPERATURE if s >= STALL_AFTER else TEMPERATURES[i % len(TEMPERATURES)] for i, s in enumerate(stalled)]
    assert chat.temperatures == expected and EXPLORE_TEMPERATURE in expected  # the stubborn model got stuck, then hotter
    # and untruncated: llama.cpp's default top-p/min-p/top-k would keep the copy of the best entry at any temperature
    assert chat.sampling == [EXPLORE_SAMPLING if t == EXPLORE_TEMPERATURE else {} for t in expected]
    decisions: list[dict[str, Any]] = [c["decisions"] for c in calls]
    bodies = [json.loads(c["request"]) for c in calls]
    assert [{k: b[k] for k in EXPLORE_SAMPLING if k in b} for b in bodies] == chat.sampling  # sent as asked, audited below
    assert [d["stalled"] for d in decisions] == stalled and [d["temperature"] for d in decisions] == expected
    assert all(c["form"] == "document" for c in calls)
    report = audit_run(run)
    assert not report.unverified and not report.leaks, report.format()


def test_a_decision_the_form_did_not_make_is_flagged(tmp_path: Path) -> None:
    run, _ = _run(tmp_path)
    tamper_call(run, 0, decisions=lambda d: {**d, "stalled": 7})  # the first call: a number the shown returns do not give
    report = audit_run(run)
    assert any("stall count 7 is not the 0 the shown returns give" in f.detail for f in report.unverified), report.format()


def test_explore_off_keeps_the_plain_schedule_and_audits_clean(tmp_path: Path) -> None:
    run, chat = _run(tmp_path, explore=False)
    assert chat.temperatures == [TEMPERATURES[i % len(TEMPERATURES)] for i in range(8)] and not any(chat.sampling)
    with open_store(run) as store:
        assert all(c["decisions"]["stalled"] == 0 for c in store.llm_calls())
    report = audit_run(run)
    assert not report.unverified and not report.leaks, report.format()
