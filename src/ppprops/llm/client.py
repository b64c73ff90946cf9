"""The LLM of an OpenAI-compatible endpoint (or of the embedded model), over the official ``openai`` SDK.

``EndpointClient`` is an ``llm.protocol.LLM``: it turns a prompt form's ``wire.forms.FormRequest``
into a request body (``RequestShape.body``: the form's payload and sampling fields, plus what the
endpoint needs: the model, the token budget, the seed, the answer's constraint), sends it to
/chat/completions or /completions, and returns every HTTP try as an ``Exchange`` for the run's
store. It never reads the form's fields one by one: a field a form adds is sent as it is. For the
embedded model it starts the shipped llama.cpp server on the first request (``connect``), so a
warm-up never waits for a model to load.

Only the request body is recorded (never headers, so never the API key), as the bytes the HTTP
client sends: an httpx request hook hands them to the recorder after the SDK has serialised the
body and before it leaves (``_announce``). ``send`` returns one
usable exchange or raises, so an HTTP error never reaches the model as if it were an answer.

- **Transient faults** (timeouts, refused or dropped connections, 429, 5xx, a garbled body, a
  200 whose body is an error with a transient code) are retried here, not in the SDK (its
  ``max_retries`` is 0): exponential backoff from ``retry_base_s`` with jitter, capped at
  ``retry_max_s``; a 429's Retry-After is honoured up to ``retry_after_cap_s``. Past
  ``transport_retries`` retries the request ends in ``LLMUnavailable``.
- **Deterministic failures** end at once in ``LLMRejected``, with the server's own message: 401,
  403, 404 (with the URL tried and the likely fix), an exhausted quota, a 400/422 that names no
  parameter this client can change, a 5xx whose body says the request itself is invalid.
- **Request adaptation**: a 400/422 that says a parameter the last request carried is unknown or
  unsupported changes that parameter once, for the rest of the run: ``seed``, a sampling field
  and ``reasoning_effort`` are dropped, ``max_tokens`` becomes ``max_completion_tokens`` when the
  server asks for it, the JSON schema (``response_format``) or grammar is dropped under
  ``--structured auto``. Under ``auto`` the schema is also dropped after ``SCHEMA_MISSES``
  answers in a row under it that were unusable and not JSON (evidence that the server ignores
  it), and restored for good when the answers without it turn out no better (``SCHEMA_TRIAL``).
  Every adaptation is a hypothesis about the server, made on what the server itself did: a
  refusal naming the parameter, answers that ignore the schema, reasoning it returns, the speed
  it answers at. When the endpoint turns out to reason (a reasoning field,
  reasoning markup, reasoning tokens) the default token budget grows to leave room for it. Each
  change is carried on the exchange that caused it (``Exchange.adaptation``), which the store
  records in the run.
- **Timeouts fitted to the budget**: the per-request timeout is ``--timeout`` or, when the
  token budget at the slowest generation speed seen so far needs longer, that time twice over
  (an adaptation like the others); before any answer the embedded model gets a prior from slow
  CPU speeds. A request that times out waits twice as long on its next try.
- **A full context**: an answer cut off (``finish_reason`` ``length``) whose usage says the
  server's context is full (``RequestShape.context_full``: prompt and answer fill the known
  context, or, with fewer completion tokens than the budget sent, add up to a usual context size or
  to the same ceiling as an earlier such answer) is marked ``Exchange.context_full``: the server's
  context, not ``max_tokens``, stopped it. An answer cut off below the budget with no such sign is
  ``Exchange.cut_short``: something cut it short (a proxy, the server), and neither a larger
  context nor a larger budget is the advice.
"""

from __future__ import annotations

import email.utils
import json
import math
import os
import random
import re
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, ExitStack, nullcontext
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from ..errors import ConfigError
from ..wire.forms import ENDPOINT_CHAT, ENDPOINT_COMPLETIONS, FormRequest, answer_budget
from ..wire.parse import read_answer, split_reasoning
from .protocol import Exchange, LLMRejected, LLMUnavailable
from .settings import LLMConfig

if TYPE_CHECKING:
    from openai import OpenAI

REASONING_ROOM = {"minimal": 1024, "low": 4096, "medium": 8192, "high": 16384}
REASONING_ROOM_UNSET = 8192
# --structured auto drops the JSON schema after this many answers in a row under it that were unusable
# and not JSON (a server that holds to a schema answers a JSON object, whatever else goes wrong:
# an answer cut short or of the wrong length is no evidence that it ignores the schema), then keeps
# checking: once SCHEMA_TRIAL answers without it are no better than the answers with it were (the
# share of usable ones), it restores the schema for good.
SCHEMA_MISSES = 2
SCHEMA_TRIAL = 3
# Per-request timeout fitted to the budget: TIMEOUT_MARGIN times the time the whole budget takes
# at the slowest speed seen (completion tokens per second of latency), rounded up to TIMEOUT_STEP_S;
# never below --timeout. Before any answer, the embedded model is assumed to read the prompt at
# EMBEDDED_PRIOR[0] and write at EMBEDDED_PRIOR[1] tokens/s (busy CPU cores: dependencies.md
# measured 1.7-13.5 tokens/s of generation under load; one thread at load 1-2 read a 7,323-token
# Humanoid-Joints document at 180 tokens/s and wrote 16 tokens/s), with CHARS_PER_TOKEN characters
# a prompt token (Gemma spends a token per digit: that document was 7,933 characters).
TIMEOUT_MARGIN = 2.0
TIMEOUT_STEP_S = 10.0
# Only answers that took at least this share of the timeout measure the speed: in a quick answer
# the fixed costs (connection, prompt) hide it, and a quick endpoint needs no longer timeout.
TIMED_SHARE = 0.1
EMBEDDED_PRIOR = (50.0, 5.0)
CHARS_PER_TOKEN = 1.0
# Tokens added to the answer budget of a chat request to an endpoint other than the embedded
# model: instruction-tuned chat models often explain before they answer (at 24 + 8 D
# tokens, Qwen2.5-Coder-1.5B was cut off in 2 of 14 answers, SmolLM2-135M in 30 of 45 without a
# schema), and each cut answer costs a correction request. The embedded model's grammar leaves
# it no room to explain, and its document form continues a list, so neither gets it.
EXPLANATION_ROOM = 512


def default_max_tokens(D: int, reasoning_effort: str | None = None, *, reasoning: bool = False,
                       explanation: bool = False, labels: bool = False) -> int:
    """Default token budget of one answer: the form's ``wire.forms.answer_budget(D, labels=labels)``;
    with ``explanation`` (a chat request to an endpoint other than the embedded model)
    ``EXPLANATION_ROOM`` more, for a short explanation before the answer; with ``reasoning_effort``
    set (other than ``none``), or ``reasoning`` (the endpoint was seen to reason), ``REASONING_ROOM``
    more, since reasoning tokens count against the same limit.
    """
    answer = answer_budget(D, labels=labels) + (EXPLANATION_ROOM if explanation else 0)
    if reasoning_effort in REASONING_ROOM:
        return answer + REASONING_ROOM[reasoning_effort]
    return answer + (REASONING_ROOM_UNSET if reasoning else 0)


@dataclass(frozen=True)
class ServerError:
    """What an endpoint said when it refused: the HTTP status (or the code of an error body), its
    own message, and the parameter it names when it says so in a field."""

    status: int | None
    message: str
    param: str | None = None
    code: str | None = None


# What a parameter this client sends may also be called in an error message (any other parameter,
# a form's sampling field included, by its own name).
_ALIASES: dict[str, tuple[str, ...]] = {"response_format": ("response_format", "json_schema", "response_schema")}
# The order in which parameters named in one refusal are changed (and the change described); a
# parameter not listed (a form's own sampling field) comes after them, in the order sent.
_ORDER = ("seed", "temperature", "max_tokens", "max_completion_tokens", "reasoning_effort", "response_format", "grammar", "stop",
          "top_p", "min_p", "top_k")
_REFUSES = re.compile(
    r"unknown|unsupported|not supported|unrecogni[sz]ed|not permitted|extra (?:inputs|fields)|cannot find field"
    r"|not allowed|does not support|unavailable|no longer supported|invalid type|unexpected (?:keyword|field|argument)"
    r"|only the default|only \S+ is allowed|not a valid (?:field|parameter)",
    re.IGNORECASE,
)
# A server error whose words say the request itself is at fault (e.g. llama.cpp's chat template
# raising on a message): asking again cannot help.
_INVALID_REQUEST = re.compile(
    r"invalid[ _]request|you have passed|raise_exception|validation error|failed to (?:deserialize|parse|apply)"
    r"|unsupported (?:parameter|value)",
    re.IGNORECASE,
)
_QUOTA = re.compile(r"insufficient_quota|exceeded your current quota|check your plan and billing|insufficient balance",
                    re.IGNORECASE)


# Error kinds after which the request may be adapted (a 400 or 422 that names a parameter).
ADAPTABLE_KINDS = ("bad_request", "http_422")


class RequestShape:
    """Everything a request carries besides the form's own fields, and how that changes as one
    client session learns its endpoint (module docstring, "Request adaptation"). It starts from the
    run's ``LLMConfig`` and changes only through ``adapt`` (a refused parameter) and ``learn``
    (a usable answer): ``EndpointClient`` drives it live, and the audit replays it on the recorded
    exchanges to know what each recorded request must hold (``privacy.reconstruct``).

    It also holds the per-request timeout (``timeout``), which is not a request field but is
    learnt the same way: from the generation speed of the answers so far (``learn``).
    """

    def __init__(self, config: LLMConfig, *, model: str, grammar_ok: bool) -> None:
        self.config = config
        self.model = model
        self.grammar_ok = grammar_ok  # the embedded llama.cpp server: grammars, a known context size
        self.structured = config.structured
        if self.structured == "auto":
            self.structured = "grammar" if grammar_ok else "json_schema"
        self.dropped: set[str] = set()  # request parameters this endpoint refused
        self.token_param = "max_tokens"  # or max_completion_tokens, when the endpoint asks for it
        self.reasoning_seen = False
        self.rate: float | None = None  # the slowest answer so far, completion tokens per second of latency
        self.fitted_timeout_s: float | None = None  # the timeout fitted to ``rate`` and the budget
        self._adapted: set[str] = set()
        self._schema_misses = 0  # answers in a row under the schema that were unusable and not JSON
        self._with_schema = [0, 0]  # (usable, all) answers under the schema, cut-off ones aside
        self._without_schema: list[int] | None = None  # the same since the schema was dropped on evidence (on trial)
        self._schema_kept = False  # restored after a trial: never dropped again on evidence
        self._ceilings: dict[int, int] = {}  # prompt + completion tokens of answers cut short -> their prompt tokens
        self._sent: tuple[str, ...] = ()  # the parameters of the last request built, in the order sent

    @classmethod
    def for_config(cls, config: LLMConfig) -> RequestShape:
        """The shape a fresh client of ``config``'s endpoint starts with: the embedded server
        (model alias, grammar accepted) or the configured one (its model, JSON schema)."""
        if config.embedded:
            from .embedded import MODEL_ALIAS

            return cls(config, model=MODEL_ALIAS, grammar_ok=True)
        assert config.model is not None
        return cls(config, model=config.model, grammar_ok=False)

    @property
    def context_size(self) -> int | None:
        """The server's context in tokens when this client knows it (the embedded server, started
        with ``--context-size``), else None."""
        return self.config.context_size if self.grammar_ok else None

    def max_tokens(self, req: FormRequest) -> int:
        """The token budget sent: ``--max-tokens`` if given, else the form's ``answer_tokens``, with
        ``EXPLANATION_ROOM`` for a form whose model may explain first when nothing constrains it
        (any endpoint but the embedded one), and room for reasoning (``REASONING_ROOM``) once it is
        asked for or seen."""
        if self.config.max_tokens:
            return self.config.max_tokens
        answer = req.answer_tokens + (EXPLANATION_ROOM if req.explains and not self.grammar_ok else 0)
        if self.config.reasoning_effort in REASONING_ROOM:
            return answer + REASONING_ROOM[self.config.reasoning_effort]
        return answer + (REASONING_ROOM_UNSET if self.reasoning_seen else 0)

    def timeout(self, req: FormRequest) -> float:
        """Seconds to wait for one answer to ``req``: ``--timeout``, or longer where the budget needs it.

        Once answers have been seen, ``fitted_timeout_s`` (``learn``): ``TIMEOUT_MARGIN`` times the
        budget at the slowest speed seen. Before that, for the embedded model only, a prior from
        ``EMBEDDED_PRIOR``: the prompt (about ``CHARS_PER_TOKEN`` characters a token) and the whole
        budget at slow-CPU speeds, so a high-dimensional task's first answer is not cut off by a
        timeout meant for a remote server."""
        wait = self.config.timeout_s
        if self.fitted_timeout_s is not None:
            return max(wait, self.fitted_timeout_s)
        if self.grammar_ok:
            prefill, generation = EMBEDDED_PRIOR
            prior = req.prompt_chars / CHARS_PER_TOKEN / prefill + self.max_tokens(req) / generation
            wait = max(wait, _round_up(TIMEOUT_MARGIN * prior))
        return wait

    def _constraint(self, req: FormRequest) -> dict[str, Any]:
        """The answer's constraint field: the form's JSON schema under ``--structured json_schema``
        (as ``response_format``); else its grammar under ``--structured grammar``, and under
        ``auto`` for a form without a schema, until the endpoint refuses it."""
        if self.structured == "json_schema" and req.json_schema is not None:
            return {"response_format": {"type": "json_schema",
                                        "json_schema": {"name": "policy_parameters", "schema": dict(req.json_schema), "strict": True}}}
        grammar_mode = self.structured == "grammar" or (self.config.structured == "auto" and req.json_schema is None)
        if req.grammar is not None and grammar_mode and "grammar" not in self.dropped:
            return {"grammar": req.grammar}
        return {}

    def body(self, req: FormRequest, seed: int | None) -> dict[str, Any]:
        """The whole request body of ``req``: the model, the form's payload and sampling fields (less
        those the endpoint refused), the token budget, the ``seed``, ``reasoning_effort`` (chat
        requests), the answer's constraint, and the form's ``stop`` for any endpoint but the
        embedded one (a base model that is not held by a grammar writes on past its answer)."""
        body: dict[str, Any] = {"model": self.model, **req.payload}
        body.update({k: v for k, v in req.sampling.items() if k not in self.dropped})
        if self.token_param not in self.dropped:
            body[self.token_param] = self.max_tokens(req)
        if seed is not None and "seed" not in self.dropped:
            body["seed"] = seed
        if req.endpoint == ENDPOINT_CHAT and self.config.reasoning_effort and "reasoning_effort" not in self.dropped:
            body["reasoning_effort"] = self.config.reasoning_effort
        body.update(self._constraint(req))
        if req.stop and not self.grammar_ok and "stop" not in self.dropped:
            body["stop"] = list(req.stop)
        self._sent = tuple(k for k in body if k not in ("model", "messages", "prompt"))
        return body

    def adapt(self, err: ServerError) -> tuple[str | None, str | None]:
        """After a refusal (``ADAPTABLE_KINDS``) of the last request built: (the change made, or
        None; a hint for the error text when no change is possible)."""
        if not _REFUSES.search(err.message):
            return None, None  # a parameter may be named, but not refused (e.g. "max_tokens is too large")
        sent = sorted(self._sent, key=lambda p: _ORDER.index(p) if p in _ORDER else len(_ORDER))  # what the last request carried
        named = [err.param] if err.param in sent else []
        if not named:
            low = err.message.lower()
            named = [p for p in sent if any(re.search(rf"(?<![a-z_]){a}(?![a-z_])", low) for a in _ALIASES.get(p, (p,)))]
        if not named:
            return None, None
        changes = []
        for p in named:
            if p in self._adapted:
                return None, f"{p} was already changed once"
            if p in ("response_format", "grammar") and self.config.structured != "auto":
                return None, f"--structured {self.config.structured} was asked for; use --structured auto or none"
            self._adapted.add(p)
            changes.append(self._apply(p, err.message))
        status = f"HTTP {err.status}" if err.status is not None else "an error body"
        return f"{'; '.join(changes)} (after {status}: {_clip(err.message, 160)})", None

    def _apply(self, param: str, message: str) -> str:
        if param in ("max_tokens", "max_completion_tokens"):
            other = "max_completion_tokens" if param == "max_tokens" else "max_tokens"
            if (other in message or param == "max_completion_tokens") and other not in self._adapted:
                self.token_param = other
                return f"sent {other} instead of {param}"
            self.dropped.add(param)
            return f"dropped {param}"
        if param == "response_format":
            self.structured = "none"
            return "dropped the JSON schema (plain answers)"
        if param == "grammar":
            self.dropped.add(param)
            if self.structured == "grammar":
                self.structured = "none"
            return "dropped the grammar"
        self.dropped.add(param)
        return f"dropped {param}"

    def learn(self, req: FormRequest, content: str | None, reasoning: str | None, *, finish_reason: str | None = None,
              reasoning_tokens: int | None = None, latency_s: float | None = None, completion_tokens: int | None = None) -> list[str]:
        """After an answer to ``req`` (HTTP-wise usable): room for reasoning once the endpoint is
        seen to reason; (``--structured auto``) the JSON schema's trial (``schema_evidence``); and a
        longer timeout when ``TIMEOUT_MARGIN`` times the budget at the slowest speed seen so far
        (``completion_tokens`` in ``latency_s`` seconds, prompt time included; only answers that
        took ``TIMED_SHARE`` of the timeout or more) is past the current one. Returns the changes
        made, in words."""
        notes = []
        saw = bool((reasoning or "").strip()) or bool(reasoning_tokens) or bool(split_reasoning(content).reasoning)
        if saw and not self.reasoning_seen:
            before = self.max_tokens(req)
            self.reasoning_seen = True
            if self.max_tokens(req) != before:
                notes.append(f"{self.token_param} raised from {before} to {self.max_tokens(req)}: the endpoint returns reasoning")
        if req.json_schema is not None and self.config.structured == "auto" and finish_reason != "length":
            notes += self.schema_evidence(req, content, reasoning, finish_reason)
        now = max(self.config.timeout_s, self.fitted_timeout_s or 0.0)
        if completion_tokens and latency_s and latency_s >= TIMED_SHARE * now:
            rate = completion_tokens / latency_s
            self.rate = rate if self.rate is None else min(self.rate, rate)
            budget = self.max_tokens(req)
            if TIMEOUT_MARGIN * budget / self.rate > now:
                need = self.fitted_timeout_s = _round_up(TIMEOUT_MARGIN * budget / self.rate)
                notes.append(f"timeout set to {need:g} s (--timeout {self.config.timeout_s:g}): answers came at "
                             f"{self.rate:.1f} tokens/s and up to {budget} tokens are asked for")
        return notes

    def schema_evidence(self, req: FormRequest, content: str | None, reasoning: str | None, finish_reason: str | None) -> list[str]:
        """Weigh one answer (not cut off) to a request of a form with a JSON schema, under
        ``--structured auto``; returns the change made, in words, if any.

        Under the schema: an unusable answer that is not even a JSON object is evidence that the
        server ignores the schema (one that holds to it answers an object, however wrong its
        numbers: an answer cut short or garbled on the way is not); ``SCHEMA_MISSES`` in a row drop
        it. Without it, after such a drop: once ``SCHEMA_TRIAL`` answers have come, and at every
        answer after, the share of usable ones is compared with the share under the schema; no
        better, and the schema is restored, for good (a refusal of it, 400/422, still drops it).
        """
        usable = read_answer(content, reasoning, req.D, finish_reason=finish_reason).ok
        if self.structured == "json_schema":
            self._with_schema[0] += usable
            self._with_schema[1] += 1
            ignored = not usable and not (content or "").lstrip().startswith("{")
            self._schema_misses = self._schema_misses + 1 if ignored else 0
            if self._schema_misses >= SCHEMA_MISSES and not self._schema_kept:
                self.structured = "none"
                self._without_schema = [0, 0]
                return [f"dropped the JSON schema (plain answers): {SCHEMA_MISSES} answers in a row under it were unusable and "
                        "not JSON, as from a server that ignores it; it comes back if the answers without it are no better"]
        elif self._without_schema is not None and "response_format" not in self._adapted:
            self._without_schema[0] += usable
            self._without_schema[1] += 1
            (u, n), (uw, nw) = self._without_schema, self._with_schema
            if n >= SCHEMA_TRIAL and u * nw <= uw * n:  # u/n <= uw/nw: no better without it
                self.structured = "json_schema"
                self._without_schema = None
                self._schema_kept = True
                self._schema_misses = 0
                return [f"restored the JSON schema: {u} of {n} answers without it were usable, against {uw} of {nw} with it; "
                        "it stays"]
        return []

    def context_full(self, max_tokens: Any, prompt_tokens: int | None, completion_tokens: int | None) -> bool:
        """Whether an answer that ended with ``finish_reason`` ``length`` was stopped by the server's
        context, on the evidence of its usage: the module's ``context_full`` (the known context
        filled, or a usual context size reached below the budget), or a total (prompt plus
        completion tokens) below the budget equal to that of an earlier answer cut short with
        another prompt length: the same ceiling twice. Remembers the answers cut short."""
        if context_full(max_tokens, prompt_tokens, completion_tokens, self.context_size):
            return True
        if not (isinstance(prompt_tokens, int) and below_budget(max_tokens, completion_tokens)):
            return False
        total = prompt_tokens + completion_tokens  # type: ignore[operator]
        seen = self._ceilings.setdefault(total, prompt_tokens)
        return seen != prompt_tokens


def below_budget(max_tokens: Any, completion_tokens: int | None) -> bool:
    """True when an answer holds fewer completion tokens than the budget sent (``max_tokens``, an int)."""
    return (isinstance(completion_tokens, int) and isinstance(max_tokens, int) and not isinstance(max_tokens, bool)
            and completion_tokens < max_tokens)


def _round_up(seconds: float) -> float:
    """``seconds`` rounded up to a whole ``TIMEOUT_STEP_S``."""
    return float(math.ceil(seconds / TIMEOUT_STEP_S) * TIMEOUT_STEP_S)


def read_api_key(llm: LLMConfig) -> str:
    """The API key from the environment variable ``llm.api_key_env`` ("not-needed" when none is
    named). Raises ConfigError when the named variable is empty or unset, before anything is sent."""
    if not llm.api_key_env:
        return "not-needed"
    key = os.environ.get(llm.api_key_env, "")
    if not key:
        raise ConfigError(f"--api-key-env names {llm.api_key_env}, but that environment variable is empty or unset")
    return key


def _ignore(*args: object) -> None:
    return None


class EndpointClient:
    """The ``LLM`` of an OpenAI-compatible endpoint: every byte sent to it goes through ``send``.

    ``send`` builds the body of a form's request (``shape``: default one for ``model`` and
    ``grammar_ok``), adapts it to the endpoint (dropped parameters, grammar support, reasoning
    output), retries transient faults with backoff, and returns each try as an ``Exchange``; the
    study's recording client stores them all, so the audit sees all of it. Without ``base_url``
    the configured endpoint is used, and for the embedded model (``config.embedded``) the shipped
    llama.cpp server is started on the first ``send`` (``on_loading()`` before, ``on_ready(seconds)``
    after) and stopped by ``close``; ``server`` replaces how: a factory of a context manager whose
    entered value has the server's ``base_url`` (``embedded.WarmServer``: a server shared by the
    processes that drive one study, left running on ``close``). ``gate`` (a grid's cap on
    concurrent requests) is held around every request. The SDK is imported on the first request,
    not before.

    Raises:
        ConfigError: a named API-key variable that is empty or unset (at construction, before
            anything is sent).
    """

    endpoints = (ENDPOINT_CHAT, ENDPOINT_COMPLETIONS)

    def __init__(self, config: LLMConfig, *, base_url: str | None = None, api_key: str | None = None, model: str | None = None,
                 grammar_ok: bool = False, shape: RequestShape | None = None, gate: AbstractContextManager[object] | None = None,
                 on_loading: Callable[[], None] = _ignore, on_ready: Callable[[float], None] = _ignore,
                 server: Callable[[], AbstractContextManager[Any]] | None = None) -> None:  # fmt: skip
        if shape is None:
            shape = RequestShape(config, model=model, grammar_ok=grammar_ok) if model is not None else RequestShape.for_config(config)
        self.config = config
        self.shape = shape
        self.model = shape.model
        self.base_url = base_url if base_url is not None else (config.base_url or "")
        self._key = api_key if api_key is not None else read_api_key(config)
        self._start_server = base_url is None and config.embedded
        self._server = server if server is not None else self._own_server
        self._on_loading, self._on_ready = on_loading, on_ready
        self.gate = gate if gate is not None else nullcontext()
        self._stack = ExitStack()
        self._lock = threading.RLock()  # the SDK client's start and the request shape, shared by a round's threads
        self._sdk: OpenAI | None = None
        self.sleep: Callable[[float], None] = time.sleep
        self._jitter = random.Random()
        self.adaptations: list[str] = []

    @property
    def url(self) -> str:
        """The URL chat requests go to."""
        return self.base_url.rstrip("/") + "/chat/completions"

    @property
    def document_url(self) -> str:
        """The URL document continuations go to (the completions endpoint)."""
        return self.base_url.rstrip("/") + "/completions"

    def _own_server(self) -> AbstractContextManager[Any]:
        from .embedded import EmbeddedServer

        return EmbeddedServer(context_size=self.config.context_size)

    def _client(self) -> OpenAI:
        """The SDK client, made on first use (starting the embedded server first when this client
        runs it; the concurrent requests of a round start it once)."""
        with self._lock:
            return self._make_client()

    def _make_client(self) -> OpenAI:
        if self._sdk is None:
            if self._start_server:
                self._on_loading()
                t0 = time.monotonic()
                server = self._stack.enter_context(self._server())
                self._on_ready(time.monotonic() - t0)
                self.base_url = server.base_url
            from openai import DefaultHttpxClient, OpenAI

            http = DefaultHttpxClient(event_hooks={"request": [_announce]})
            self._sdk = OpenAI(base_url=self.base_url, api_key=self._key, timeout=self.config.timeout_s, max_retries=0,
                               http_client=http)
            self._stack.callback(self._sdk.close)
        return self._sdk

    def start(self) -> EndpointClient:
        """Connect now (starting the embedded server when this client runs it) rather than on the
        first ``send``; returns the client, whose ``base_url`` is then the server's."""
        self._client()
        return self

    def body(self, req: FormRequest, *, seed: int | None = None) -> dict[str, Any]:
        """The request body ``send`` would send now for ``req`` (``RequestShape.body``)."""
        return self.shape.body(req, seed)

    def send(self, request: FormRequest, *, seed: int | None = None, before_try: Callable[[str, int], None] | None = None,
             after_failure: Callable[[Exchange], None] | None = None) -> Exchange:
        """One usable answer (``ok``) to ``request``, after adapting the request and retrying transient faults.

        The failed tries come back in ``failures``. ``before_try(body, retry)`` is called with
        the exact JSON body of each try just before its bytes leave (the recording client writes
        it ahead there; if it raises, that try is not sent), and ``after_failure(ex)`` with each
        failed try as soon as it failed, as it will be in ``failures``. Raises ``LLMUnavailable`` past the
        retry bound and ``LLMRejected`` for deterministic failures, both carrying the failed
        tries; ``LLMError`` when the embedded server fails to start.
        """
        client = self._client()
        with self.gate:
            return self._request(request, seed, client, before_try, after_failure)

    def _request(self, req: FormRequest, seed: int | None, client: OpenAI, before_try: Callable[[str, int], None] | None = None,
                 after_failure: Callable[[Exchange], None] | None = None) -> Exchange:
        failures: list[Exchange] = []

        def failed(ex: Exchange) -> None:
            failures.append(ex)
            if after_failure is not None:
                after_failure(ex)

        transient = 0
        retry = 0
        stretch = 1.0  # each timed-out try of this request waits twice as long the next time
        while True:
            with self._lock:
                body = self.shape.body(req, seed)
                wait = stretch * self.shape.timeout(req)
            ex, retry_after, err = self._attempt(client, req, body, retry=retry, timeout_s=wait, before_try=before_try)
            if ex.ok:
                return replace(self._after_answer(req, ex), failures=tuple(failures))
            if ex.error_kind == "timeout":
                stretch *= 2.0
            if err is not None and ex.error_kind in ADAPTABLE_KINDS:
                with self._lock:
                    change, hint = self.shape.adapt(err)
                if change is not None:
                    self.adaptations.append(change)
                    failed(replace(ex, adaptation=change, error=f"{ex.error}; adapted: {change}"))
                    retry += 1
                    continue
                if hint:
                    ex = replace(ex, error=f"{ex.error} ({hint})")
            failed(ex)
            if not _retryable(ex.error_kind):
                raise LLMRejected(f"LLM endpoint refused the request: {ex.error}", tuple(failures))
            if transient >= self.config.transport_retries:
                raise LLMUnavailable(f"LLM endpoint failed {len(failures)} times in a row (last: {ex.error})", tuple(failures))
            self.sleep(self.backoff(transient, retry_after))
            transient += 1
            retry += 1

    def backoff(self, retry: int, retry_after: float | None) -> float:
        """Seconds to wait before retry ``retry + 1``: Retry-After (capped) if given, else
        exponential with "equal jitter" (half fixed, half random), so clients do not retry in step."""
        cfg = self.config
        if retry_after is not None:
            return min(max(retry_after, 0.0), cfg.retry_after_cap_s)
        d = min(cfg.retry_max_s, cfg.retry_base_s * (2.0**retry))
        return d / 2 + self._jitter.uniform(0.0, d / 2)

    def _after_answer(self, req: FormRequest, ex: Exchange) -> Exchange:
        """Learn from a usable exchange (``RequestShape.learn``); a change rides on the exchange."""
        with self._lock:
            notes = self.shape.learn(req, ex.content, ex.reasoning, finish_reason=ex.finish_reason, reasoning_tokens=ex.reasoning_tokens,
                                     latency_s=ex.latency_s, completion_tokens=ex.completion_tokens)
        if not notes:
            return ex
        self.adaptations += notes
        return replace(ex, adaptation="; ".join(notes))

    # -- one HTTP round trip ------------------------------------------------------------------
    def _attempt(self, client: OpenAI, req: FormRequest, body: dict[str, Any], *, retry: int, timeout_s: float,
                 before_try: Callable[[str, int], None] | None = None) -> tuple[Exchange, float | None, ServerError | None]:
        """One HTTP round trip of ``body`` (a chat or completions body of ``req``), waiting at most
        ``timeout_s`` for the answer, never raising for endpoint faults: (exchange, Retry-After
        seconds, what the server said when it refused). ``before_try`` sees the body first."""
        import openai

        document = req.endpoint == ENDPOINT_COMPLETIONS
        url = self.document_url if document else self.url
        request = json.dumps(body)  # what is recorded if the SDK fails before the request is made
        prompt_chars = req.prompt_chars
        known = _SDK_DOCUMENT_ARGS if document else _SDK_ARGS
        sdk_args = {k: v for k, v in body.items() if k in known}
        extra = {k: v for k, v in body.items() if k not in known} or None
        sent: list[str] = []
        unrecorded: list[BaseException] = []  # before_try's own error (an SDK may wrap what its send raises)

        def announce(wire: str) -> None:  # the body's bytes, about to leave (_announce)
            sent.append(wire)
            if before_try is not None:
                try:
                    before_try(wire, retry)
                except BaseException as e:
                    unrecorded.append(e)
                    raise

        t0 = time.perf_counter()

        def failed(kind: str, error: str, response: str | None = None) -> Exchange:
            return Exchange(request, response, None, None, prompt_chars, None, None, time.perf_counter() - t0, False,
                            error, error_kind=kind, retry=retry)

        def refused(err: ServerError, response: str | None, shown: int) -> Exchange:
            kind = _kind(err)
            where = f"HTTP {shown}" if shown == err.status else f"HTTP {shown} with an error body (code {err.code})"
            text = f"{kind}: {where} from {url}: {err.message}"
            if err.status == 404:
                text += f"; {_url_hint(self.base_url, self.model)}"
            return failed(kind, text, response)

        try:
            api: Any = client.completions if document else client.chat.completions
            _wire.announce = announce
            try:
                raw = api.with_raw_response.create(**sdk_args, extra_body=extra, timeout=timeout_s)
            except BaseException:
                if unrecorded:  # not written ahead, so not sent: the recorder's error, as it was raised
                    raise unrecorded[0] from None
                raise
            finally:
                _wire.announce = None
                request = sent[-1] if sent else request
            latency = time.perf_counter() - t0
            text = raw.http_response.text
        except openai.APITimeoutError:
            return failed("timeout", f"timeout: no answer within {timeout_s:g} s from {url}"), None, None
        except openai.APIConnectionError as e:
            kind = "refused" if _is_refused(e) else "dropped"
            return failed(kind, f"{kind}: {_cause(e)} at {url}"), None, None
        except openai.APIStatusError as e:
            err_body = _body_text(e)
            err = server_error(e.status_code, err_body)
            after = _retry_after(e)
            ex = refused(err, err_body, e.status_code)
            if after is not None:
                ex = replace(ex, error=f"{ex.error} (Retry-After {after:g} s)")
            return ex, after, err
        try:
            doc = json.loads(text)
        except ValueError as e:
            return failed("bad_response", f"bad_response: the body is not JSON ({_short(e)})", text), None, None
        if isinstance(doc, dict) and doc.get("error") and not doc.get("choices"):
            err = server_error(None, text)  # an error delivered with HTTP 200 (OpenRouter does this)
            return refused(err, text, 200), None, err
        try:
            completion = raw.parse()
            choice = completion.choices[0]
            if document:
                content, reasoning = choice.text, None
                if not isinstance(content, str):
                    raise TypeError("the choice has no text")
            else:
                message = choice.message
                extra_fields = message.model_extra or {}
                content = message.content
                reasoning = next((v for k in ("reasoning_content", "reasoning")
                                  if isinstance(v := extra_fields.get(k), str) and v.strip()), None)
        except Exception as e:  # a 200 whose body is not a completion (no choices, cut, wrong shape)
            what = "completion" if document else "chat completion"
            return failed("bad_response", f"bad_response: not a {what} ({e.__class__.__name__}: {_short(e)})", text), None, None
        finish = choice.finish_reason
        if finish == "error":
            return failed("endpoint_error", f"endpoint_error: the answer ended with finish_reason error ({url})", text), None, None
        usage = completion.usage
        details = getattr(usage, "completion_tokens_details", None) if usage else None
        prompt_tokens = usage.prompt_tokens if usage else None
        completion_tokens = usage.completion_tokens if usage else None
        budget = body.get(self.shape.token_param)
        full = finish == "length" and self.shape.context_full(budget, prompt_tokens, completion_tokens)
        short = finish == "length" and not full and below_budget(budget, completion_tokens)
        return Exchange(request=request, response=text, content=content, reasoning=reasoning, prompt_chars=prompt_chars,
                        prompt_tokens=prompt_tokens, completion_tokens=completion_tokens, latency_s=latency, ok=True, retry=retry,
                        finish_reason=finish, reasoning_tokens=getattr(details, "reasoning_tokens", None),
                        context_full=full, cut_short=short), None, None

    def close(self) -> None:
        """Close the HTTP connection pool, and stop the embedded server if this client started it."""
        self._stack.close()
        self._sdk = None


def connect(config: LLMConfig, *, gate: AbstractContextManager[object] | None = None, on_loading: Callable[[], None] = _ignore,
            on_ready: Callable[[float], None] = _ignore, server: Callable[[], AbstractContextManager[Any]] | None = None) -> EndpointClient:
    """The ``LLM`` a study talks to when it is given none: the configured endpoint's client, or the
    embedded model's, started on the first request (by ``server`` when given: ``EndpointClient``).
    Raises ConfigError when the named API-key variable is empty or unset."""
    return EndpointClient(config, gate=gate, on_loading=on_loading, on_ready=on_ready, server=server)


_wire = threading.local()  # .announce: the recorder of the try this thread is making (EndpointClient._attempt)


def _announce(request: Any) -> None:
    """httpx's request hook: hand the request's body, the exact bytes about to be sent, to the
    try this thread is making. It runs after the SDK has serialised the body and before a byte
    leaves, so the write-ahead record is the body sent; a failure to record stops the request."""
    announce = getattr(_wire, "announce", None)
    if announce is not None:
        announce(request.content.decode("utf-8"))


# Arguments the SDK takes by name; anything else in the body (grammar) goes as extra_body.
_SDK_ARGS = frozenset({"model", "messages", "temperature", "max_tokens", "max_completion_tokens", "seed",
                       "reasoning_effort", "response_format"})
_SDK_DOCUMENT_ARGS = frozenset({"model", "prompt", "temperature", "max_tokens", "seed", "top_p"})


# The smallest context a server is run with; the usual sizes are powers of two from here on
# (llama.cpp's -c, per slot; Ollama's num_ctx; a model's trained context).
SMALLEST_CONTEXT = 512


def context_full(max_tokens: Any, prompt_tokens: int | None, completion_tokens: int | None,
                 context_size: int | None = None) -> bool:
    """Whether an answer that ended with ``finish_reason`` ``length`` was stopped by the server's
    context rather than by the answer budget, on the evidence of its usage alone: prompt and answer
    together reach ``context_size`` (when the client knows the server's context); or, with fewer
    completion tokens than ``max_tokens`` (the budget sent), they add up to a usual context size (a
    power of two of at least ``SMALLEST_CONTEXT`` tokens). An answer cut short below the budget
    with any other total is no evidence of a full context (a proxy may cut an answer; see
    ``RequestShape.context_full`` for a ceiling seen twice). Unknown token counts: False."""
    if not isinstance(completion_tokens, int) or not isinstance(prompt_tokens, int):
        return False
    total = prompt_tokens + completion_tokens
    if context_size is not None:
        return total >= context_size
    return below_budget(max_tokens, completion_tokens) and total >= SMALLEST_CONTEXT and total & (total - 1) == 0


def server_error(status: int | None, text: str | None) -> ServerError:
    """Read an error body in any of the shapes servers use: OpenAI's ``{"error": {...}}``, Google's
    list-wrapped one, FastAPI's ``{"detail": [...]}``, vLLM's ``{"object": "error", ...}``, a bare
    ``{"error": "text"}``, or plain text. ``status`` None takes the code from the body."""
    raw = (text or "").strip()
    try:
        doc: Any = json.loads(raw) if raw else None
    except ValueError:
        doc = None
    if isinstance(doc, list) and doc:
        doc = doc[0]
    message, param, code = raw, None, None
    if isinstance(doc, dict):
        err = doc.get("error", doc)
        if isinstance(err, dict):
            message = str(err.get("message") or err.get("msg") or err.get("status") or raw)
            param = err.get("param") if isinstance(err.get("param"), str) else None
            code = err.get("code") if err.get("code") is not None else err.get("type")
        elif isinstance(err, str):
            message = err
        if isinstance(doc.get("detail"), list):  # FastAPI / pydantic validation errors
            parts = [f"{'.'.join(map(str, d.get('loc', [])))}: {d.get('msg', '')}" for d in doc["detail"] if isinstance(d, dict)]
            message = "; ".join(parts) or message
        elif isinstance(doc.get("detail"), str):
            message = doc["detail"]
    if status is None:
        try:
            status = int(str(code))
        except (TypeError, ValueError):
            status = None
        status = status if status is not None and 100 <= status <= 599 else None
    message = " ".join(message.split()) or "(no message)"
    return ServerError(status=status, message=_clip(message, 400), param=param,
                       code=None if code is None else str(code))


def _kind(err: ServerError) -> str:
    s = err.status
    if s is None:
        return "endpoint_error"
    if s == 400:
        return "bad_request"
    if s == 429:
        return "quota_exhausted" if _QUOTA.search(f"{err.code} {err.message}") else "rate_limited"
    if s >= 500 and _INVALID_REQUEST.search(err.message):
        return "invalid_request"
    return f"http_{s}"


def _url_hint(base_url: str, model: str) -> str:
    """The likely fix for a 404: a --base-url that includes /chat/completions or lacks /v1."""
    base = base_url.rstrip("/")
    path = urlsplit(base).path
    if path.endswith("/chat/completions"):
        return f"--base-url must stop before /chat/completions (ppprops adds it): try --base-url {base[: -len('/chat/completions')]}"
    if not re.search(r"/v\d", path):
        return f"OpenAI-compatible APIs usually live under /v1: try --base-url {base}/v1"
    return f"check --base-url and that the server serves --model {model}"


def _clip(text: str, n: int) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def _retryable(kind: str | None) -> bool:
    """Transient faults only: a 401, 403 or 404, a refused or invalid request or an exhausted quota
    will not heal by asking again."""
    if kind in ("timeout", "refused", "dropped", "rate_limited", "bad_response", "endpoint_error"):
        return True
    if kind is not None and kind.startswith("http_"):
        code = int(kind[5:])
        return code >= 500 or code in (408, 409, 425)
    return False


def _retry_after(e: Exception) -> float | None:
    """Seconds from Retry-After-Ms or Retry-After (seconds or an HTTP date), if the answer has one."""
    resp = getattr(e, "response", None)
    headers = getattr(resp, "headers", None)
    if headers is None:
        return None
    ms = headers.get("retry-after-ms")
    if ms is not None:
        try:
            return float(ms) / 1000.0
        except ValueError:
            pass
    value = headers.get("retry-after")
    if value is None:
        return None
    try:
        return float(value)
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


def _cause(e: BaseException) -> str:
    """The innermost exception's class, e.g. ConnectError or RemoteProtocolError."""
    inner: BaseException = e
    while inner.__cause__ is not None:
        inner = inner.__cause__
    return inner.__class__.__name__


def _is_refused(e: BaseException) -> bool:
    inner: BaseException | None = e
    while inner is not None:
        if isinstance(inner, ConnectionRefusedError) or inner.__class__.__name__ == "ConnectError":
            return True
        inner = inner.__cause__ or inner.__context__
    return False


def _body_text(e: Exception) -> str | None:
    resp = getattr(e, "response", None)
    return getattr(resp, "text", None)


def _short(e: Exception) -> str:
    text = str(e).splitlines()[0] if str(e) else e.__class__.__name__
    return text[:200]
