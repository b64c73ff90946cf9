"""The one recording client: every try of every request goes to the store as it happens.

``RecordingLLM`` wraps the study's ``LLM`` (an endpoint's client, the embedded model's, or a
user's own model) and is the only way a proposer reaches it. It is an ``LLM`` itself: ``send``
takes a form's request (``wire.forms.FormRequest``), sends it, and records each try, failed ones
included, with the iteration and attempt it belongs to, the form's name and the public decisions
the form took. A proposer cannot forget to record: it never sees an unrecorded exchange. After
reading an answer it may add its verdict (``judged``: the parse error, where the answer came
from), which updates the recorded row.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Collection, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Protocol

from .protocol import LLM, Exchange, LLMUnavailable

if TYPE_CHECKING:
    from ..wire.forms import FormRequest


class CallLog(Protocol):
    """Where calls are recorded (``store.RunStore``)."""

    def add_llm_call(self, iteration: int, attempt: int, ex: Any, parse_error: str | None, *, form: str,
                     decisions: Mapping[str, Any] | None = None) -> int:
        """Record one try; returns its row id."""
        ...

    def annotate_llm_call(self, call_id: int, *, parse_error: str | None, answer_source: str | None) -> None:
        """Add the proposer's verdict on a recorded answer."""
        ...


class RecordingLLM:
    """An ``LLM`` that sends through ``inner`` and records every try in ``log``.

    ``on_first_use`` runs before the first request (the study marks where a new client session
    begins, so the audit replays its request shape from there).
    """

    def __init__(self, inner: LLM, log: CallLog, *, on_first_use: Callable[[], None] | None = None) -> None:
        self.inner = inner
        self.log = log
        self._on_first_use = on_first_use
        self._ids: dict[int, int] = {}  # id(exchange) -> recorded row
        self._lock = threading.Lock()  # one recording at a time; the requests themselves run concurrently

    @property
    def endpoints(self) -> Collection[str]:
        """The endpoints the wrapped model serves."""
        return self.inner.endpoints

    def send(self, request: FormRequest, *, seed: int | None = None) -> Exchange:
        """Send ``request`` and record it (and each failed try before it).

        Returns the exchange as recorded (``ok`` or not: a model may return a refused one);
        raises ``LLMUnavailable``/``LLMRejected`` as the wrapped model does, after recording the tries.
        """
        with self._lock:
            if self._on_first_use is not None:
                hook, self._on_first_use = self._on_first_use, None
                hook()
        try:
            ex = self.inner.send(request, seed=seed)
        except LLMUnavailable as e:
            for t in e.failures:
                self._record(t, request)
            raise
        for t in ex.failures:
            self._record(t, request)
        ex = replace(ex, failures=())  # recorded: the proposer needs the answer, not the tries
        call_id = self._record(ex, request)
        with self._lock:
            self._ids[id(ex)] = call_id
        return ex

    def _record(self, ex: Exchange, req: FormRequest) -> int:
        with self._lock:
            return self.log.add_llm_call(req.iteration, req.attempt, ex, None, form=req.form, decisions=dict(req.decisions))

    def judged(self, ex: Exchange, *, parse_error: str | None, answer_source: str | None) -> None:
        """Record the proposer's verdict on ``ex`` (an exchange ``send`` returned)."""
        with self._lock:
            call_id = self._ids.pop(id(ex), None)
            if call_id is not None:
                self.log.annotate_llm_call(call_id, parse_error=parse_error, answer_source=answer_source)

    def close(self) -> None:
        """Nothing of its own: the study closes the wrapped model."""
