"""The one recording client: every try of every request goes to the store as it happens.

``RecordingChat`` wraps whatever answers (the ``ChatClient`` of an endpoint, the embedded
model's, or a user's own chat object) and is the only way a proposer reaches it: ``send`` takes a
form's request (``wire.forms.FormRequest``), sends it, and records each HTTP try, failed ones
included, with the iteration and attempt it belongs to, the form's name and the public decisions
the form took. A proposer cannot forget to record: it never sees an unrecorded exchange. After
reading an answer it may add its verdict (``judged``: the parse error, where the answer came
from), which updates the recorded row.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any, Protocol

from ..wire.forms import COMPLETIONS, FormRequest
from .client import Exchange, LLMUnavailable


class CallLog(Protocol):
    """Where calls are recorded (``store.RunStore``)."""

    def add_llm_call(self, iteration: int, attempt: int, ex: Any, parse_error: str | None, *, form: str | None = None,
                     decisions: Mapping[str, Any] | None = None) -> int:
        """Record one HTTP try; returns its row id."""
        ...

    def annotate_llm_call(self, call_id: int, *, parse_error: str | None, answer_source: str | None) -> None:
        """Add the proposer's verdict on a recorded answer."""
        ...


class RecordingChat:
    """Sends form requests through ``inner`` and records every try in ``log``.

    ``inner`` has ``complete(messages, *, D, seed)`` (chat completions) and, to serve the
    completions endpoint, ``complete_document(prompt, *, D, seed, grammar, temperature)``; both
    return an ``Exchange`` (its failed tries in ``failures``) or raise ``LLMUnavailable`` /
    ``LLMRejected`` carrying them. ``on_first_use`` runs before the first request (the study marks
    where a new client session begins, so the audit replays its request shape from there).
    """

    def __init__(self, inner: Any, log: CallLog, *, on_first_use: Any = None) -> None:
        self.inner = inner
        self.log = log
        self._on_first_use = on_first_use
        self._ids: dict[int, int] = {}  # id(exchange) -> recorded row

    @property
    def completes_documents(self) -> bool:
        """True when the wrapped model can continue documents (the completions endpoint)."""
        return callable(getattr(self.inner, "complete_document", None))

    def send(self, req: FormRequest, *, D: int, seed: int | None, iteration: int, attempt: int) -> Exchange:
        """Send one request for ``D`` numbers and record it (and each failed try before it).

        Returns the exchange as recorded (``ok`` or not: a chat object may return a refused one);
        raises ``LLMUnavailable``/``LLMRejected`` as the inner client does, after recording the tries.
        """
        if self._on_first_use is not None:
            hook, self._on_first_use = self._on_first_use, None
            hook()
        try:
            if req.endpoint == COMPLETIONS:
                more = {"sampling": dict(req.sampling)} if req.sampling else {}  # only when the form asks: older chat objects
                ex = self.inner.complete_document(req.prompt, D=D, seed=seed, grammar=req.grammar, temperature=req.temperature, **more)
            else:
                ex = self.inner.complete(req.messages, D=D, seed=seed)
        except LLMUnavailable as e:
            for t in e.failures:
                self._record(t, req, iteration, attempt)
            raise
        for t in ex.failures:
            self._record(t, req, iteration, attempt)
        ex = replace(ex, failures=())  # recorded: the proposer needs the answer, not the tries
        self._ids[id(ex)] = self._record(ex, req, iteration, attempt)
        return ex

    def _record(self, ex: Exchange, req: FormRequest, iteration: int, attempt: int) -> int:
        return self.log.add_llm_call(iteration, attempt, ex, None, form=req.form, decisions=dict(req.decisions))

    def judged(self, ex: Exchange, *, parse_error: str | None, answer_source: str | None) -> None:
        """Record the proposer's verdict on ``ex`` (an exchange ``send`` returned)."""
        call_id = self._ids.pop(id(ex), None)
        if call_id is not None:
            self.log.annotate_llm_call(call_id, parse_error=parse_error, answer_source=answer_source)

    def count_tokens(self, text: str) -> int:
        """The wrapped model's token estimate (R2PO's context check); nothing is sent."""
        return int(self.inner.count_tokens(text))

    def close(self) -> None:
        """Nothing of its own: the study closes the wrapped client."""
