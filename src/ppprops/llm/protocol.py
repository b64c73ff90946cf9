"""The one LLM protocol: what answers a study's requests, and what one round trip is.

``LLM`` is the only interface between a proposer and a model. A study talks to one (the
configured endpoint's ``llm.client.EndpointClient``, the embedded model's, or an object a user
passes as ``llm=``) through the recording client (``llm.recording.RecordingLLM``, an ``LLM``
itself), which stores every try before the proposer sees the answer. A request is a prompt
form's ``wire.forms.FormRequest``; an answer (or a failed try) is an ``Exchange``.

Your own model, in a few lines::

    from ppprops.llm import LLM, Exchange
    from ppprops.wire.forms import ENDPOINT_CHAT

    class MyModel:
        endpoints = (ENDPOINT_CHAT,)          # the forms it can serve, by endpoint
        def send(self, request, *, seed=None):
            text = my_generate(request.messages, seed=seed)      # {"params": [...]}
            return Exchange.answer(request, text)
        def close(self):
            pass
"""

from __future__ import annotations

import json
from collections.abc import Collection
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from ..errors import LLMError

if TYPE_CHECKING:
    from ..wire.forms import FormRequest


@dataclass(frozen=True)
class Exchange:
    """One HTTP round trip (or one answer of a model that is not behind HTTP), as the store records it.

    ``request`` is the JSON body sent (never headers, so never an API key); ``content`` the
    answer's text (a chat message's content, or a document's continuation); ``reasoning`` the
    reasoning text a server returns apart; ``ok`` False for a failed try, with ``error`` and
    ``error_kind`` (timeout | refused | dropped | rate_limited | quota_exhausted | bad_response |
    bad_request | invalid_request | endpoint_error | http_NNN). ``retry`` is 0 for a request's first
    try, n for its n-th retry; ``failures`` the failed tries before this one; ``adaptation`` a
    change to later requests this exchange caused; ``context_full`` marks an answer stopped by the
    server's context rather than by the answer budget, on the evidence of its usage; ``cut_short``
    one that ended with ``finish_reason`` ``length`` below the budget with no such evidence (a
    proxy or the server cut it short).
    """

    request: str
    response: str | None
    content: str | None
    reasoning: str | None
    prompt_chars: int
    prompt_tokens: int | None
    completion_tokens: int | None
    latency_s: float
    ok: bool
    error: str | None = None
    error_kind: str | None = None
    retry: int = 0
    answer_source: str | None = None  # set by the proposer: content | reasoning
    failures: tuple[Exchange, ...] = ()
    finish_reason: str | None = None  # the choice's: stop | length | content_filter | ...
    reasoning_tokens: int | None = None  # usage.completion_tokens_details.reasoning_tokens, when reported
    adaptation: str | None = None
    context_full: bool = False
    cut_short: bool = False

    @classmethod
    def answer(cls, request: FormRequest, content: str, *, body: str | None = None, latency_s: float = 0.0,
               finish_reason: str | None = "stop") -> Exchange:
        """A usable answer ``content`` to ``request`` from a model that is not an HTTP endpoint.
        ``body`` is what was sent, as JSON (default: the form's payload and sampling fields)."""
        sent = body if body is not None else json.dumps({**request.payload, **request.sampling})
        return cls(request=sent, response=None, content=content, reasoning=None, prompt_chars=request.prompt_chars,
                   prompt_tokens=None, completion_tokens=None, latency_s=latency_s, ok=True, finish_reason=finish_reason)


class LLMUnavailable(LLMError):
    """A request kept failing with transient faults past the retry bound. Carries the failed tries."""

    def __init__(self, message: str, failures: tuple[Exchange, ...]) -> None:
        super().__init__(message)
        self.failures = failures

    @property
    def kind(self) -> str:
        """The last failed try's error kind (``timeout``, ``refused``, ``http_5xx``, ...), or ``unknown``."""
        return (self.failures[-1].error_kind or "unknown") if self.failures else "unknown"


class LLMRejected(LLMUnavailable):
    """The endpoint refused the request for good (401, 403, 404, an invalid request, an exhausted
    quota, ...): retrying or skipping cannot help."""


@runtime_checkable
class LLM(Protocol):
    """What answers a study's requests.

    ``endpoints`` are the endpoints it serves (``wire.forms.ENDPOINT_CHAT``, and
    ``ENDPOINT_COMPLETIONS`` for a model that continues documents: the document form needs it).
    ``send`` answers one ``FormRequest`` with the sampling ``seed`` (None: unseeded) and returns an
    ``ok`` Exchange (its failed tries in ``failures``), or raises ``LLMUnavailable`` /
    ``LLMRejected`` carrying them. ``close`` releases what it holds (an embedded server it started).
    """

    @property
    def endpoints(self) -> Collection[str]:
        """The endpoints it serves: ``wire.forms.ENDPOINT_CHAT``, and ``ENDPOINT_COMPLETIONS`` for a model that continues documents."""
        ...

    def send(self, request: FormRequest, *, seed: int | None = None) -> Exchange:
        """Answer ``request``; see the class docstring."""
        ...

    def close(self) -> None:
        """Release the model (stop a server this object started)."""
        ...


__all__ = ["LLM", "Exchange", "LLMRejected", "LLMUnavailable"]
