"""The one recording client (``ppprops.llm.recording.RecordingLLM``): every try of every request is
stored with its form and decisions before the proposer sees the answer. A real store, a model
object in-process: no HTTP, no model."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from ppprops.llm.protocol import LLM, Exchange, LLMUnavailable
from ppprops.llm.recording import RecordingLLM
from ppprops.store import RunStore
from ppprops.wire.forms import ENDPOINT_CHAT

from support import chat_request


class Scripted:
    """An LLM whose answers are given in advance: an Exchange, or an exception to raise."""

    endpoints = (ENDPOINT_CHAT,)

    def __init__(self, *outcomes: Exchange | Exception) -> None:
        self.outcomes = list(outcomes)
        self.sent: list[tuple[object, int | None]] = []

    def send(self, request, *, seed=None):  # type: ignore[no-untyped-def]
        self.sent.append((request, seed))
        out = self.outcomes.pop(0)
        if isinstance(out, Exception):
            raise out
        return out

    def close(self) -> None:
        pass


def _failed(kind: str) -> Exchange:
    return Exchange("{}", None, None, None, 1, None, None, 0.1, False, f"{kind}: x", error_kind=kind)


def test_it_is_an_llm_and_records_each_try_before_the_answer(tmp_path: Path) -> None:
    req = replace(chat_request([{"role": "user", "content": "P"}], 3, iteration=4, attempt=1), decisions={"correction": "d"})
    answer = replace(Exchange.answer(req, '{"params": [1, 2, 3]}'), failures=(_failed("timeout"), _failed("http_503")))
    inner = Scripted(answer)
    starts: list[int] = []
    with RunStore(tmp_path / "run.sqlite") as store:
        rec = RecordingLLM(inner, store, on_first_use=lambda: starts.append(1))
        assert isinstance(rec, LLM) and rec.endpoints == (ENDPOINT_CHAT,)
        ex = rec.send(req, seed=9)
        rec.judged(ex, parse_error=None, answer_source="content")
        calls = store.llm_calls()
    assert inner.sent == [(req, 9)] and ex.failures == () and starts == [1]
    assert [(c["iteration"], c["attempt"], c["ok"], c["error_kind"], c["form"]) for c in calls] == [
        (4, 1, 0, "timeout", "chat"), (4, 1, 0, "http_503", "chat"), (4, 1, 1, None, "chat")]
    assert all(c["decisions"] == {"correction": "d"} for c in calls) and calls[-1]["answer_source"] == "content"


def test_tries_of_a_request_that_stays_down_are_recorded_then_the_error_raised(tmp_path: Path) -> None:
    req = chat_request([{"role": "user", "content": "P"}], 3)
    down = LLMUnavailable("down", (_failed("refused"), _failed("refused")))
    with RunStore(tmp_path / "run.sqlite") as store:
        rec = RecordingLLM(Scripted(down), store)
        with pytest.raises(LLMUnavailable):
            rec.send(req)
        assert [c["error_kind"] for c in store.llm_calls()] == ["refused", "refused"]


def test_the_first_use_hook_runs_once(tmp_path: Path) -> None:
    req = chat_request([{"role": "user", "content": "P"}], 1)
    starts: list[int] = []
    with RunStore(tmp_path / "run.sqlite") as store:
        rec = RecordingLLM(Scripted(Exchange.answer(req, "{}"), Exchange.answer(req, "{}")), store, on_first_use=lambda: starts.append(1))
        rec.send(req)
        rec.send(req)
        assert len(store.llm_calls()) == 2
    assert starts == [1]
