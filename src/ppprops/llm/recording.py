"""The one recording client: every try of every request goes to the store before it is sent.

``RecordingLLM`` wraps the study's ``LLM`` (an endpoint's client, the embedded model's, or a
user's own model) and is the only way a proposer reaches it. It is an ``LLM`` itself: ``send``
takes a form's request (``wire.forms.FormRequest``), writes each try to the store before its
bytes leave (write-ahead: ``CallLog.begin_llm_call``), sends it, and completes each try with what
came back (``complete_llm_call``), failed ones included, with the iteration and attempt it belongs
to, the form's name and the public decisions the form took. A process killed while a request is
in flight leaves that request in the store, unanswered, where the audit reads it like any other.
A proposer cannot forget to record: it never sees an unrecorded exchange. After reading an
answer it may add its verdict (``judged``: the parse error, where the answer came from), which
updates the recorded row.

A try is completed as soon as its outcome is known: a model that announces its tries also
reports each failed one as it fails (``after_failure``); the others' tries are completed when
the request ends. Until then, and for good if the process dies first, a try reads as unanswered.

Write-ahead is per try, and the tries of one ``send`` are that call's own: several threads may
send at once (requests in flight together), each writing its own tries ahead.

A wrapped model that sends over the wire itself announces each try before its bytes leave: its
``send`` takes ``before_try(body, retry)``, called with
the exact body of each try, and ``after_failure(exchange)``, called with each failed try
(``llm.client.EndpointClient``). Any other model is written ahead
once per ``send``, with the form's payload and sampling fields (what ``Exchange.answer`` records
by default), and completed with the exchange it returns.
"""

from __future__ import annotations

import inspect
import json
import threading
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Protocol

from .protocol import LLM, Exchange, LLMUnavailable

if TYPE_CHECKING:
    from ..wire.forms import FormRequest
    from .pacing import Pacer


class CallLog(Protocol):
    """Where calls are recorded (``store.RunStore``)."""

    def begin_llm_call(self, iteration: int, attempt: int, request: str, *, prompt_chars: int, retry: int = 0, form: str,
                       decisions: Mapping[str, Any] | None = None) -> int:
        """Write one try ahead (before it is sent); returns its row id."""
        ...

    def complete_llm_call(self, call_id: int, ex: Any) -> None:
        """Complete a try written ahead with what came back."""
        ...

    def add_llm_call(self, iteration: int, attempt: int, ex: Any, parse_error: str | None, *, form: str,
                     decisions: Mapping[str, Any] | None = None) -> int:
        """Record one whole try; returns its row id."""
        ...

    def annotate_llm_call(self, call_id: int, *, parse_error: str | None, answer_source: str | None) -> None:
        """Add the proposer's verdict on a recorded answer."""
        ...


def announces_tries(model: LLM) -> bool:
    """True when ``model.send`` takes ``before_try`` and ``after_failure`` (it sends over the wire
    itself and announces each try: ``llm.client.EndpointClient``). Read off the signature, so a
    subclass whose ``send`` does not take them is written ahead once per request."""
    try:
        params = inspect.signature(model.send).parameters
    except (TypeError, ValueError):
        return False
    return "before_try" in params and "after_failure" in params


class RecordingLLM:
    """An ``LLM`` that writes every try to ``log`` before sending it through ``inner``, and
    completes it with the answer after. Safe to call from several threads at once.

    ``on_first_use`` runs before the first request (the study marks where a new client session
    begins, so the audit replays its request shape from there). ``pacer`` (``llm.pacing.Pacer``)
    holds each request before its first try is written ahead and sent, and hears when it ended.
    """

    def __init__(self, inner: LLM, log: CallLog, *, on_first_use: Callable[[], None] | None = None,
                 pacer: Pacer | None = None) -> None:
        self.inner = inner
        self.log = log
        self.pacer = pacer
        self._on_first_use = on_first_use
        self._lock = threading.Lock()  # guards the first-use hook and ``_ids``
        self._ids: dict[int, int] = {}  # id(exchange) -> recorded row

    @property
    def endpoints(self) -> Collection[str]:
        """The endpoints the wrapped model serves."""
        return self.inner.endpoints

    def send(self, request: FormRequest, *, seed: int | None = None) -> Exchange:
        """Write ``request`` ahead, send it, and complete its record (and that of each failed try before it).

        Returns the exchange as recorded (``ok`` or not: a model may return a refused one);
        raises ``LLMUnavailable``/``LLMRejected`` as the wrapped model does, after completing the
        tries; ``StoreError`` when a try cannot be written ahead (then it is not sent). Whatever
        else ends the call (an interrupt, a killed process) leaves the tries sent so far in the
        store as unanswered.
        """
        with self._lock:
            hook, self._on_first_use = self._on_first_use, None
        if hook is not None:
            hook()
        if self.pacer is not None:
            self.pacer.before_request()
        ahead: list[int] = []  # this call's tries written ahead, in the order sent
        done: list[int] = []  # those completed so far

        def before_try(body: str, retry: int) -> None:
            ahead.append(self.log.begin_llm_call(request.iteration, request.attempt, body, prompt_chars=request.prompt_chars,
                                                 retry=retry, form=request.form, decisions=dict(request.decisions)))

        def after_failure(ex: Exchange) -> None:
            if len(done) < len(ahead):
                self.log.complete_llm_call(ahead[len(done)], replace(ex, failures=()))
                done.append(ahead[len(done)])

        try:
            if announces_tries(self.inner):
                ex = self.inner.send(request, seed=seed, before_try=before_try, after_failure=after_failure)  # type: ignore[call-arg]
            else:
                before_try(json.dumps({**request.payload, **request.sampling}), 0)
                ex = self.inner.send(request, seed=seed)
        except LLMUnavailable as e:
            self._complete(ahead, done, e.failures, request)
            if self.pacer is not None:
                self.pacer.answered()
            raise
        if self.pacer is not None:
            self.pacer.answered()
        rows = self._complete(ahead, done, (*ex.failures, ex), request)
        ex = replace(ex, failures=())  # recorded: the proposer needs the answer, not the tries
        with self._lock:
            self._ids[id(ex)] = rows[-1]
        return ex

    def _complete(self, ahead: list[int], done: list[int], tries: Sequence[Exchange], req: FormRequest) -> list[int]:
        """Complete the tries written ahead with ``tries``, in order (the first ``len(done)`` are
        complete already); a try the model reports beyond those it announced is recorded whole.
        Returns the rows of ``tries``."""
        rows = []
        for k, t in enumerate(tries):
            t = replace(t, failures=())
            if k < len(done):
                rows.append(done[k])
            elif k < len(ahead):
                self.log.complete_llm_call(ahead[k], t)
                rows.append(ahead[k])
            else:
                rows.append(self.log.add_llm_call(req.iteration, req.attempt, t, None, form=req.form, decisions=dict(req.decisions)))
        return rows

    def judged(self, ex: Exchange, *, parse_error: str | None, answer_source: str | None) -> None:
        """Record the proposer's verdict on ``ex`` (an exchange ``send`` returned)."""
        with self._lock:
            call_id = self._ids.pop(id(ex), None)
        if call_id is not None:
            self.log.annotate_llm_call(call_id, parse_error=parse_error, answer_source=answer_source)

    def close(self) -> None:
        """Nothing of its own: the study closes the wrapped model."""
