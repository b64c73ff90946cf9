"""The one recording client (``ppprops.llm.recording.RecordingLLM``): every try of every request is
stored with its form and decisions before the proposer sees the answer. A real store, a model
object in-process: no HTTP, no model."""

from __future__ import annotations

import json
import threading
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


# -- write-ahead: every try is in the store before its bytes leave ------------------------------------------
class Announcing:
    """A model that sends over the wire itself (as ``EndpointClient``): it announces each try's body
    before 'sending' it, and looks at the store at that moment."""

    endpoints = (ENDPOINT_CHAT,)

    def __init__(self, store: RunStore, tries: list[tuple[str, Exchange | None]], *, answer: Exchange | BaseException) -> None:
        self.store, self.tries, self.answer = store, tries, answer
        self.seen: list[list[tuple[str, bool, str | None]]] = []  # the store's calls as each try left

    def send(self, request, *, seed=None, before_try=None, after_failure=None):  # type: ignore[no-untyped-def]
        failures = []
        for retry, (body, failed) in enumerate(self.tries):
            before_try(body, retry)
            self.seen.append([(c["request"], c["answered"], c["error_kind"]) for c in self.store.llm_calls()])
            if failed is not None:
                failures.append(replace(failed, request=body, retry=retry))
                after_failure(failures[-1])
        if isinstance(self.answer, BaseException):
            raise self.answer
        return replace(self.answer, request=self.tries[-1][0], retry=len(self.tries) - 1, failures=tuple(failures))

    def close(self) -> None:
        pass


def test_each_try_is_written_before_it_leaves_and_completed_with_its_answer(tmp_path: Path) -> None:
    req = replace(chat_request([{"role": "user", "content": "P"}], 3, iteration=2), decisions={"correction": "d"})
    with RunStore(tmp_path / "run.sqlite") as store:
        model = Announcing(store, [('{"try": 0}', _failed("timeout")), ('{"try": 1}', None)],
                           answer=Exchange.answer(req, '{"params": [1, 2, 3]}', latency_s=0.5))
        ex = RecordingLLM(model, store).send(req, seed=3)
        calls = store.llm_calls()
    assert model.seen == [  # each try is in the store, unanswered, when it leaves; the failed one before it is complete
        [('{"try": 0}', False, "unanswered")],
        [('{"try": 0}', True, "timeout"), ('{"try": 1}', False, "unanswered")],
    ]
    assert [(c["request"], c["answered"], c["ok"], c["error_kind"], c["retry"], c["content"], c["latency_s"]) for c in calls] == [
        ('{"try": 0}', True, False, "timeout", 0, None, 0.1), ('{"try": 1}', True, True, None, 1, '{"params": [1, 2, 3]}', 0.5)]
    assert all(c["decisions"] == {"correction": "d"} and c["iteration"] == 2 for c in calls) and ex.failures == ()


def test_a_request_cut_off_mid_flight_stays_recorded_unanswered(tmp_path: Path) -> None:
    """What a killed process leaves: the try written ahead, never completed (an interrupt here; SIGKILL
    in tests/test_write_ahead.py)."""
    req = chat_request([{"role": "user", "content": "P"}], 3, iteration=5)
    with RunStore(tmp_path / "run.sqlite") as store:
        model = Announcing(store, [('{"try": 0}', _failed("http_503")), ('{"try": 1}', None)], answer=KeyboardInterrupt())
        with pytest.raises(KeyboardInterrupt):
            RecordingLLM(model, store).send(req)
    with RunStore(tmp_path / "run.sqlite") as store:  # as the next process reads it
        calls = store.llm_calls()
    assert [(c["request"], c["answered"], c["ok"], c["error_kind"], c["iteration"]) for c in calls] == [
        ('{"try": 0}', True, False, "http_503", 5), ('{"try": 1}', False, False, "unanswered", 5)]
    assert calls[1]["error"].startswith("unanswered: the request was sent and no answer was recorded")


def test_a_model_that_does_not_announce_its_tries_is_written_ahead_once_per_request(tmp_path: Path) -> None:
    req = chat_request([{"role": "user", "content": "P"}], 3)
    seen: list[list[tuple[str, bool]]] = []

    with RunStore(tmp_path / "run.sqlite") as store:
        class Looking(Scripted):
            def send(self, request, *, seed=None):  # type: ignore[no-untyped-def]
                seen.append([(c["request"], c["answered"]) for c in store.llm_calls()])
                return super().send(request, seed=seed)

        ex = RecordingLLM(Looking(Exchange.answer(req, "{}", body='{"as": "sent"}')), store).send(req)
        calls = store.llm_calls()
    ahead = json.dumps({**req.payload, **req.sampling})
    assert seen == [[(ahead, False)]]  # the form's payload and sampling fields, before the model ran
    assert [(c["request"], c["answered"], c["ok"]) for c in calls] == [('{"as": "sent"}', True, True)] and ex.ok


def test_requests_in_flight_together_from_threads_are_each_written_ahead(tmp_path: Path) -> None:
    """P requests sent at once from P threads: all P are in the store, unanswered, while all P are in
    flight, and each is completed with its own answer."""
    P = 4
    together = threading.Barrier(P, timeout=30)
    snapshot: list[list[tuple[str, bool]]] = []

    with RunStore(tmp_path / "run.sqlite") as store:
        class Parallel:
            endpoints = (ENDPOINT_CHAT,)
        
            def send(self, request, *, seed=None, before_try=None, after_failure=None):  # type: ignore[no-untyped-def]
                body = json.dumps({"n": request.iteration})
                before_try(body, 0)
                if together.wait() == 0:  # every thread's request is out: look at the store once
                    snapshot.append(sorted((c["request"], c["answered"]) for c in store.llm_calls()))
                together.wait()
                return replace(Exchange.answer(request, f"answer {request.iteration}"), request=body)

            def close(self) -> None:
                pass

        rec = RecordingLLM(Parallel(), store)
        answers: dict[int, str | None] = {}

        def one(i: int) -> None:
            ex = rec.send(chat_request([{"role": "user", "content": f"P{i}"}], 3, iteration=i))
            rec.judged(ex, parse_error=f"verdict {i}", answer_source=None)
            answers[i] = ex.content

        threads = [threading.Thread(target=one, args=(i,)) for i in range(P)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
        calls = store.llm_calls()
    assert snapshot == [sorted((json.dumps({"n": i}), False) for i in range(P))]
    assert answers == {i: f"answer {i}" for i in range(P)}
    assert sorted((c["iteration"], c["request"], c["content"], c["parse_error"], c["answered"]) for c in calls) == [
        (i, json.dumps({"n": i}), f"answer {i}", f"verdict {i}", True) for i in range(P)]
