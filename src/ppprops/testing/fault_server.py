"""A fault-injecting OpenAI-compatible server (chat completions, and completions for the document
form), for tests and the soak benchmark.

It listens on 127.0.0.1 only. Each request either passes (to an upstream server, or answered
with a valid random vector of the requested length) or, with probability ``fault_rate``, gets
one fault drawn uniformly from ``kinds``:

transport faults
    ``delay`` (a slow but valid answer), ``timeout`` (stalls, then drops the connection),
    ``http_429`` (with Retry-After), ``http_500``, ``http_503``, ``drop`` (headers and half the
    body, then the connection closes), ``reset`` (the connection closes with no answer),
    ``bad_json`` (a 200 whose body is not JSON), ``error_body`` (a 200 whose body is an error
    object with code ``error_body_code`` and no choices, as OpenRouter sends when a provider
    fails after the status line went out: openrouter.ai/docs/api-reference/errors)
bad answers (HTTP 200, well-formed envelope)
    ``empty``, ``truncated``, ``wrong_length``, ``nan``, ``inf``, ``huge``, ``prose``,
    ``several_vectors``, ``reasoning_only`` (empty content, the vector in ``reasoning_content``),
    ``refusal``

Both endpoints take the same faults: ``/chat/completions`` (``messages``) answers in a chat
completion, ``/completions`` (``prompt``, the document form of ``ppprops.wire.document``) in a
text completion whose text continues the document's open list; its bad answers are the same
kinds written as such a continuation (``garble_document``).

Requests that get no fault are answered by a persona (``personas``, drawn per request; see
``ppprops.testing.personas``: vLLM, Ollama and llama.cpp serving gpt-oss, harmony markup, R1
think tags, DeepSeek, OpenAI reasoning models, Gemini, chatty chat models, a full context, a
slow CPU server, ...; on ``/completions`` the personas of ``DOCUMENT_PERSONAS``, such as a base
model that writes on past the list), or passed upstream, or answered with a plain random vector.
``answers()`` lists the new vectors the personas meant to propose. ``v1_only`` answers 404 for
any path but ``/v1/chat/completions`` and ``/v1/completions``, as Ollama does.

The vector length D is read from the request: the JSON schema's ``minItems``, the llama.cpp
grammar's repetition count (or the labels of the document form's continuation grammar), the
prompt's "with D numbers" (or integers) / "exactly D ... numbers", or the last history entry of a document.
Decisions come from one seeded generator in arrival order, so a serial client sees the same
fault sequence for the same seed. The server stops by itself after ``max_requests`` requests or
``max_seconds`` seconds. ``GET /stats`` returns the counts, among them the most completions
requests in flight at once (read and not yet answered: a client's concurrency cap, seen from the
server) and the most served at once (holding a slot of ``concurrency``: in their latency or being
answered), which tell how requests overlapped without reading a clock.

For tests of what a client does around a request rather than with its answer:

``fixed_status`` / ``fixed_body``
    every request that gets no fault is answered with this status and JSON body (a server quirk:
    a quota 429, a 400 naming no parameter, ...) instead of a persona, upstream or random vector.
``hold_after``
    the requests after the first ``hold_after`` are held open, unanswered, until ``release()``
    (``POST /release``) lets them go on as usual, or until the server stops and drops them: a
    request in flight at a moment the test chooses (a Ctrl-C during an LLM call).
``record``
    every request received is kept, byte for byte (request line, headers, blank line, body), for
    ``received()``: what crossed the wire, to compare with what the client recorded.
``burst``
    requests ``first`` to ``last`` (numbered from 1) always get a fault (of ``kinds``), the others
    one at ``fault_rate``: a run of bad answers at a moment the test chooses.
``latency_s`` / ``concurrency``
    every completions request takes ``latency_s`` seconds before its answer (a slow model), and at
    most ``concurrency`` are served at once (None: all), the rest waiting in line, as a server with
    that many slots does: what a round of ``--parallel`` requests gains is measured against it
    (``most_served`` in the stats: how many were served side by side).

Command line (prints ``listening URL`` first, the stats as JSON when it stops)::

    python -m ppprops.testing.fault_server --port 0 --fault-rate 0.3 --synthetic
    python -m ppprops.testing.fault_server --port 0 --fault-rate 0 --personas harmony_markup,r1_open_think
    python -m ppprops.testing.fault_server --upstream http://127.0.0.1:8080/v1 --kinds http_429,drop
    python -m ppprops.testing.fault_server --fault-rate 0 --fixed-status 429 --fixed-body '{"error": {"code": 429}}'
    python -m ppprops.testing.fault_server --fault-rate 0 --hold-after 2   # then: curl -X POST URL/release
"""

from __future__ import annotations

import argparse
import http.server
import json
import random
import re
import signal
import socket
import sys
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from ..wire.forms import DOCUMENT
from .personas import DOCUMENT_PERSONAS, PERSONAS, QUIRK_PERSONAS, Reply, labelled_list, read_turn, text_completion

CHAT_PERSONAS = {**PERSONAS, **QUIRK_PERSONAS}
KNOWN_PERSONAS = tuple(dict.fromkeys([*CHAT_PERSONAS, *DOCUMENT_PERSONAS]))

TRANSPORT_KINDS = ("delay", "timeout", "http_429", "http_500", "http_503", "drop", "reset", "bad_json", "error_body")
ANSWER_KINDS = (
    "empty", "truncated", "wrong_length", "nan", "inf", "huge", "prose", "several_vectors", "reasoning_only", "refusal",
)
ALL_KINDS = TRANSPORT_KINDS + ANSWER_KINDS


@dataclass
class FaultConfig:
    """What to inject and how. Times are in seconds."""

    fault_rate: float = 0.3
    kinds: tuple[str, ...] = ALL_KINDS
    seed: int = 0
    upstream: str | None = None  # None: answer with valid random vectors (synthetic)
    delay_max_s: float = 0.3  # a "delay" fault waits uniform(0, delay_max_s)
    timeout_s: float = 2.0  # a "timeout" fault stalls this long, then drops the connection
    retry_after_s: float = 1.0  # the Retry-After header of a 429
    max_requests: int | None = None
    max_seconds: float = 600.0
    value_range: float = 3.0  # synthetic answers draw uniform(-value_range, value_range)
    default_dim: int | None = None  # D when the request does not tell
    personas: tuple[str, ...] = ()  # answer healthy requests as one of these (drawn per request); () = plain vectors
    v1_only: bool = False  # 404 for any path but /v1/chat/completions and /v1/completions
    error_body_code: int = 502  # the code inside an "error_body" fault
    fixed_status: int | None = None  # answer every request that gets no fault with this status and fixed_body
    fixed_body: str = "{}"  # the JSON body of those answers (with fixed_status)
    hold_after: int | None = None  # hold the requests after the first hold_after open until release() or stop
    record: bool = False  # keep every request received, byte for byte, for FaultServer.received()
    burst: tuple[int, int] | None = None  # requests first..last (from 1) always get a fault: a burst of them
    latency_s: float = 0.0  # every completions request waits this long before its answer
    concurrency: int | None = None  # at most this many completions requests served at once (None: no limit)

    def validate(self) -> None:
        """Check the settings (``FaultServer`` calls it).

        Raises:
            ValueError: ``fault_rate`` outside [0, 1], no or unknown ``kinds``, unknown ``personas``,
                personas together with an upstream, an upstream that is not ``http://``,
                ``max_requests`` < 1 or ``max_seconds`` <= 0; a ``fixed_status`` outside 100-599, with
                personas or an upstream, or whose ``fixed_body`` is not JSON; ``hold_after`` < 0; a
                ``burst`` whose first request is not between 1 and its last.
        """
        if not (0.0 <= self.fault_rate <= 1.0):
            raise ValueError(f"fault rate must be in [0, 1], got {self.fault_rate}")
        unknown = [k for k in self.kinds if k not in ALL_KINDS]
        if unknown or not self.kinds:
            raise ValueError(f"unknown fault kinds {unknown}; choose from {', '.join(ALL_KINDS)}")
        bad = [p for p in self.personas if p not in KNOWN_PERSONAS]
        if bad:
            raise ValueError(f"unknown personas {bad}; choose from {', '.join(KNOWN_PERSONAS)}")
        if self.personas and self.upstream is not None:
            raise ValueError("personas answer by themselves; they do not go with an upstream")
        if self.upstream is not None and not self.upstream.startswith("http://"):
            raise ValueError(f"upstream must be an http:// URL, got {self.upstream!r}")
        if self.max_requests is not None and self.max_requests < 1:
            raise ValueError(f"max requests must be >= 1, got {self.max_requests}")
        if not (self.max_seconds > 0):
            raise ValueError(f"max seconds must be > 0, got {self.max_seconds}")
        if self.fixed_status is not None:
            if not (100 <= self.fixed_status <= 599):
                raise ValueError(f"fixed status must be an HTTP status (100-599), got {self.fixed_status}")
            if self.personas or self.upstream is not None:
                raise ValueError("a fixed answer answers by itself; it does not go with personas or an upstream")
            try:
                json.loads(self.fixed_body)
            except ValueError as e:
                raise ValueError(f"fixed body must be JSON: {e}") from None
        if not (self.latency_s >= 0.0):
            raise ValueError(f"latency must be >= 0 seconds, got {self.latency_s}")
        if self.concurrency is not None and self.concurrency < 1:
            raise ValueError(f"concurrency must be >= 1, got {self.concurrency}")
        if self.hold_after is not None and self.hold_after < 0:
            raise ValueError(f"hold after must be >= 0, got {self.hold_after}")
        if self.burst is not None and not (1 <= self.burst[0] <= self.burst[1]):
            raise ValueError(f"a burst is requests first..last with 1 <= first <= last, got {self.burst[0]}..{self.burst[1]}")


@dataclass
class _State:
    config: FaultConfig
    rng: random.Random
    lock: threading.Lock = field(default_factory=threading.Lock)
    stop: threading.Event = field(default_factory=threading.Event)
    requests: int = 0
    injected: Counter[str] = field(default_factory=Counter)
    passed: int = 0
    started: float = field(default_factory=time.monotonic)
    personas: Counter[str] = field(default_factory=Counter)
    answers: list[tuple[int, str, list[float]]] = field(default_factory=list)  # (request, persona, new vector)
    released: threading.Event = field(default_factory=threading.Event)  # ends the hold of hold_after
    received: list[bytes] = field(default_factory=list)  # every request, byte for byte (with record)
    in_flight: int = 0
    most_in_flight: int = 0
    serving: int = 0  # completions requests holding a slot of concurrency (or, without it, past reading)
    most_served: int = 0
    slots: threading.Semaphore | None = None  # concurrency: the requests served at once

    def __post_init__(self) -> None:
        if self.config.concurrency is not None:
            self.slots = threading.Semaphore(self.config.concurrency)

    def draw(self) -> tuple[int, str | None, random.Random, str]:
        """Request number, fault kind (None = pass), a generator for this request's values, and
        the persona that answers if it passes."""
        with self.lock:
            self.requests += 1
            n = self.requests
            burst = self.config.burst is not None and self.config.burst[0] <= n <= self.config.burst[1]
            faulty = self.rng.random() < self.config.fault_rate or burst  # one draw either way: the sequence stays the same
            kind = self.rng.choice(self.config.kinds) if faulty else None
            if kind is None:
                self.passed += 1
            else:
                self.injected[kind] += 1
            sub = random.Random(self.rng.getrandbits(64))
            persona = self.rng.choice(self.config.personas) if self.config.personas else "plain"
        return n, kind, sub, persona

    def answered(self, n: int, persona: str, reply: Reply) -> None:
        """Log a reply; ``persona`` may also be the name of the bad-answer fault that made it."""
        with self.lock:
            if persona in KNOWN_PERSONAS:
                self.personas[persona] += 1
            if reply.answer is not None:
                self.answers.append((n, persona, list(reply.answer)))

    def arrived(self) -> None:
        """A completions request is in flight (until ``left``)."""
        with self.lock:
            self.in_flight += 1
            self.most_in_flight = max(self.most_in_flight, self.in_flight)

    def left(self) -> None:
        """A request is no longer in flight: its answer starts going out, or its connection is dropped."""
        with self.lock:
            self.in_flight -= 1

    def served(self, step: int) -> None:
        """A completions request starts (+1) or ends (-1) being served: its latency wait and its answer."""
        with self.lock:
            self.serving += step
            self.most_served = max(self.most_served, self.serving)

    def stats(self) -> dict[str, Any]:
        with self.lock:
            return {
                "requests": self.requests,
                "passed": self.passed,
                "injected": dict(sorted(self.injected.items())),
                "injected_total": sum(self.injected.values()),
                "personas": dict(sorted(self.personas.items())),
                "most_in_flight": self.most_in_flight,
                "most_served": self.most_served,
                "elapsed_s": round(time.monotonic() - self.started, 3),
            }


_SCHEMA_DIM = re.compile(r"\{(\d+)\}")
_GRAMMAR_LABEL = re.compile(r'"(?:,)?(\d+):"')
_PROMPT_DIM = re.compile(r"(?:with|exactly|holding exactly) (\d+) (?:finite )?(?:numbers|integers)")


def requested_dim(body: dict[str, Any], default: int | None = None) -> int | None:
    """D from the JSON schema, the grammar (the chat form's repetition count, or the labels of the
    document form's continuation grammar), the prompt text, or the last entry of a document (in
    that order)."""
    try:
        schema = body["response_format"]["json_schema"]["schema"]
        return int(schema["properties"]["params"]["minItems"])
    except (KeyError, TypeError, ValueError):
        pass
    grammar = body.get("grammar")
    if isinstance(grammar, str):
        labels = _GRAMMAR_LABEL.findall(grammar)
        if labels:  # one item per value: labelled ones, and with row labels the bare '","' ones between them
            root = grammar.split("\n", 1)[0]
            return len(labels) + root.count('"," ')
        m = _SCHEMA_DIM.search(grammar)
        return int(m.group(1)) + 1 if m else 1
    prompt = body.get("prompt")
    if isinstance(prompt, str):
        entries = DOCUMENT.entries(prompt)
        return len(entries[-1].params) if entries else default
    for msg in reversed(body.get("messages") or []):
        content = msg.get("content") if isinstance(msg, dict) else None
        if isinstance(content, str):
            m = _PROMPT_DIM.search(content)
            if m:
                return int(m.group(1))
    return default


def _vector(rng: random.Random, D: int, span: float) -> list[float]:
    return [round(rng.uniform(-span, span), 2) for _ in range(D)]


def _params_json(values: list[Any]) -> str:
    return '{"params": [' + ", ".join(str(v) for v in values) + "]}"


# Bad answers a client can still use: the vector they carry (logged with the personas' answers).
USABLE_BAD_ANSWERS = ("huge", "reasoning_only")


def garble(kind: str, D: int, rng: random.Random, span: float) -> tuple[str | None, str | None]:
    """(content, reasoning_content) of a bad answer of the given kind."""
    good = _params_json(_vector(rng, D, span))
    if kind == "empty":
        return "", None
    if kind == "truncated":
        return good[: max(12, len(good) // 2)], None
    if kind == "wrong_length":
        n = D + rng.choice([-1, 1, 3]) if D > 1 else 2
        return _params_json(_vector(rng, max(1, n), span)), None
    if kind == "nan":
        vals: list[Any] = _vector(rng, D, span)
        vals[rng.randrange(D)] = "NaN"
        return _params_json(vals), None
    if kind == "inf":
        vals = list[Any](_vector(rng, D, span))
        vals[rng.randrange(D)] = "-Infinity" if rng.random() < 0.5 else "Infinity"
        return _params_json(vals), None
    if kind == "huge":
        vals = list[Any](_vector(rng, D, span))
        vals[rng.randrange(D)] = rng.choice(["1e308", "-9.9e307", "123456789012345678901234567890"])
        return _params_json(vals), None
    if kind == "prose":
        return "I would increase the weights on the pole angle and its velocity to react faster.", None
    if kind == "several_vectors":
        return "Option A: " + _params_json(_vector(rng, D, span)) + "\nOption B: " + _params_json(_vector(rng, D, span)), None
    if kind == "reasoning_only":
        return "", "Let me think about the history. The best policy is last. I propose: " + good
    if kind == "refusal":
        return "I'm sorry, but I can't help with choosing these parameters.", None
    raise ValueError(f"not an answer fault: {kind}")


def garble_document(kind: str, D: int, rng: random.Random, span: float) -> str:
    """The continuation text of a bad answer of the given kind, for the document form's open list
    (``0:v,1:v,...]``). Kinds with no such form of their own are written as their nearest one:
    ``reasoning_only`` as a ``<think>`` block and nothing else, ``several_vectors`` as the list and a
    second entry after it (the first list is the answer: usable)."""
    good = labelled_list(_vector(rng, D, span))
    if kind == "empty":
        return ""
    if kind == "truncated":
        return good[: max(4, len(good) // 2)].rstrip("]")
    if kind == "wrong_length":
        n = D + rng.choice([-1, 1, 3]) if D > 1 else 2
        return labelled_list(_vector(rng, max(1, n), span))
    if kind in ("nan", "inf", "huge"):
        vals: list[Any] = _vector(rng, D, span)
        vals[rng.randrange(D)] = {"nan": "nan", "inf": rng.choice(["inf", "-inf"]), "huge": "1e308"}[kind]
        return labelled_list(vals)
    if kind == "prose":
        return "the pole angle weights should grow]"
    if kind == "several_vectors":
        return good + "\n\nreturn: 1.00\nparams: [" + labelled_list(_vector(rng, D, span))
    if kind == "reasoning_only":
        return "<think>the best entry is the last one; change a few of its values</think>"
    if kind == "refusal":
        return "I'm sorry, but I can't help with that.]"
    raise ValueError(f"not an answer fault: {kind}")


# Bad document answers a client can still use: the list they start with.
USABLE_BAD_DOCUMENT_ANSWERS = ("huge", "several_vectors")


def _completion(content: str | None, reasoning: str | None, model: str, n: int) -> dict[str, Any]:
    message: dict[str, Any] = {"role": "assistant", "content": content}
    if reasoning is not None:
        message["reasoning_content"] = reasoning
    completion_tokens = len((content or "") + (reasoning or "")) // 4 + 1
    return {
        "id": f"chatcmpl-fault-{n}",
        "object": "chat.completion",
        "created": int(time.time()),
        "model": model,
        "choices": [{"index": 0, "message": message, "finish_reason": "stop"}],
        "usage": {"prompt_tokens": 0, "completion_tokens": completion_tokens, "total_tokens": completion_tokens},
    }


class _Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    state: _State  # set on the subclass made per server
    _in_flight = False  # this connection's current request is counted in flight

    def log_message(self, *args: object) -> None:
        pass

    def finish(self) -> None:
        try:
            super().finish()
        except OSError:
            pass  # the socket was hung up on purpose

    # -- responses ------------------------------------------------------------------------
    def _send(self, status: int, data: bytes, headers: dict[str, str] | None = None, *, partial: bool = False,
              content_type: str = "application/json") -> None:
        self._left()  # before a byte goes out: a client that waits for this answer never sees the request still in flight
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(data)))
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        if partial:
            self.end_headers()
            self.wfile.write(data[: len(data) // 2])
            self.wfile.flush()
            self._hang_up()
            return
        self.end_headers()
        self.wfile.write(data)

    def _send_json(self, status: int, obj: dict[str, Any], headers: dict[str, str] | None = None) -> None:
        self._send(status, json.dumps(obj).encode(), headers)

    def _error(self, status: int, message: str, headers: dict[str, str] | None = None) -> None:
        self._send_json(status, {"error": {"message": message, "type": "fault_injection", "code": status}}, headers)

    def _hang_up(self) -> None:
        """Close the socket at once, so the client sees a dropped connection."""
        self._left()
        self.close_connection = True
        try:
            self.connection.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def _left(self) -> None:
        if self._in_flight:
            self._in_flight = False
            self.state.left()

    def _record(self, raw: bytes) -> None:
        """Keep the request as it came (request line, headers, blank line, body) when ``record`` is on."""
        if self.state.config.record:
            head = f"{self.command} {self.path} {self.request_version}\r\n" + "".join(f"{k}: {v}\r\n" for k, v in self.headers.items())
            with self.state.lock:
                self.state.received.append(head.encode() + b"\r\n" + raw)

    def _hold(self) -> bool:
        """Wait until ``release()`` (True) or the server stops (False)."""
        st = self.state
        while not st.released.wait(0.05):
            if st.stop.is_set():
                return False
        return True

    # -- routes ---------------------------------------------------------------------------
    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        if self.path.rstrip("/").endswith("/stats"):
            self._send_json(200, self.state.stats())
            return
        self._record(b"")
        if self.path.rstrip("/").endswith("/models"):
            self._send_json(200, {"object": "list", "data": [{"id": "fault-synthetic", "object": "model"}]})
        else:
            self._error(404, f"no route {self.path}")

    def do_POST(self) -> None:  # noqa: N802
        length = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(length) if length else b""
        st = self.state
        cfg = st.config
        path = self.path.split("?")[0].rstrip("/")
        if path.endswith("/release"):  # the control route of hold_after
            st.released.set()
            self._send_json(200, {"released": True})
            return
        self._record(raw)
        if cfg.v1_only and path not in ("/v1/chat/completions", "/v1/completions"):
            self._send(404, b"404 page not found", content_type="text/plain")  # Go's default, as Ollama answers
            return
        if path not in ("/v1/chat/completions", "/chat/completions", "/v1/completions", "/completions"):
            self._error(404, f"no route {self.path}")
            return
        self._in_flight = True
        st.arrived()
        try:
            self._completions(raw, path)
        finally:
            self._left()

    def _completions(self, raw: bytes, path: str) -> None:
        st, cfg = self.state, self.state.config
        document = not path.endswith("/chat/completions")
        n, kind, rng, persona = st.draw()
        if cfg.max_requests is not None and n > cfg.max_requests:
            self._error(503, "the fault server's request budget is spent")
            st.stop.set()
            return
        try:
            body = json.loads(raw or b"{}")
            if not isinstance(body, dict):
                raise ValueError("not an object")
        except ValueError:
            self._error(400, "request body is not a JSON object")
            return
        if document != isinstance(body.get("prompt"), str):
            what = "a prompt string" if document else "messages"
            self._error(400, f"{path} takes {what}")
            return
        if cfg.hold_after is not None and n > cfg.hold_after and not self._hold():
            self._hang_up()  # the server stopped while the request was held
            return
        model = str(body.get("model") or "fault-synthetic")
        if st.slots is not None:
            st.slots.acquire()
        st.served(+1)
        try:
            if cfg.latency_s > 0:
                st.stop.wait(cfg.latency_s)
            self._answer(body, raw, model, n, kind, rng, persona, path=path)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up first (it timed out): nothing to do
        finally:
            st.served(-1)
            if st.slots is not None:
                st.slots.release()

    def _answer(self, body: dict[str, Any], raw: bytes, model: str, n: int, kind: str | None, rng: random.Random,
                persona: str = "plain", *, path: str = "/v1/chat/completions") -> None:
        st, cfg = self.state, self.state.config
        document = not path.endswith("/chat/completions")
        if kind == "timeout":
            st.stop.wait(cfg.timeout_s)
            self._hang_up()
            return
        if kind == "reset":
            self._hang_up()
            return
        if kind == "http_429":
            self._error(429, "rate limited (injected)", {"Retry-After": f"{cfg.retry_after_s:g}"})
            return
        if kind in ("http_500", "http_503"):
            self._error(int(kind[-3:]), "server error (injected)")
            return
        if kind == "bad_json":
            self._send(200, b'{"id": "chatcmpl-garbled", "choices": [{"message": <<not json>>')
            return
        if kind == "error_body":
            self._send_json(200, {"error": {"message": "Provider returned error (injected)", "code": cfg.error_body_code},
                                  "user_id": "user_fault"})
            return
        if kind == "delay":
            st.stop.wait(rng.uniform(0.0, cfg.delay_max_s))
        D = requested_dim(body, cfg.default_dim)
        if kind in ANSWER_KINDS and document:
            if D is None:
                self._error(400, "cannot tell the vector length D from the request")
                return
            continuation = garble_document(kind, D, rng, cfg.value_range)
            vector = None
            if kind in USABLE_BAD_DOCUMENT_ANSWERS:
                first = continuation.split("]")[0]
                vector = [float(item.split(":")[1]) for item in first.split(",")]
            reply = text_completion(_bare_turn(model, n), continuation, answer=vector)
            st.answered(n, kind, reply)
            self._send(200, reply.body)
            return
        if kind in ANSWER_KINDS:
            if D is None:
                self._error(400, "cannot tell the vector length D from the request")
                return
            content, reasoning = garble(kind, D, rng, cfg.value_range)
            data = json.dumps(_completion(content, reasoning, model, n)).encode()
            vector = None
            if kind in USABLE_BAD_ANSWERS:
                text = content if kind == "huge" else (reasoning or "").split("I propose: ")[-1]
                vector = [float(v) for v in json.loads(text or "{}")["params"]]
            st.answered(n, kind, Reply(200, data, answer=vector))
            self._send(200, data)
            return
        # pass (or "drop": a valid answer cut off mid-body): the fixed answer, the upstream's, or a random vector
        drop = kind == "drop"
        if cfg.fixed_status is not None:
            self._send(cfg.fixed_status, cfg.fixed_body.encode(), partial=drop)
            return
        if cfg.upstream is not None:
            status, data = self._forward(raw, path)
            self._send(status, data, partial=drop)
            return
        if D is None:
            self._error(400, "cannot tell the vector length D from the request")
            return
        turn = read_turn(body, D, _vector(rng, D, cfg.value_range), rng, n)
        if document:
            reply = DOCUMENT_PERSONAS.get(persona, DOCUMENT_PERSONAS["plain"])(turn)
        else:
            reply = CHAT_PERSONAS.get(persona, PERSONAS["plain"])(turn)
        st.answered(n, persona, reply if not drop else Reply(reply.status, reply.body))  # a dropped answer proposes nothing
        self._send(reply.status, reply.body, partial=drop, content_type=reply.content_type)

    def _forward(self, raw: bytes, path: str) -> tuple[int, bytes]:
        assert self.state.config.upstream is not None
        url = self.state.config.upstream.rstrip("/") + ("/chat/completions" if path.endswith("/chat/completions")
                                                        else "/completions")
        req = urllib.request.Request(url, data=raw, method="POST", headers={"Content-Type": "application/json"})
        auth = self.headers.get("Authorization")
        if auth:
            req.add_header("Authorization", auth)
        try:
            with urllib.request.urlopen(req, timeout=600) as resp:
                return resp.status, resp.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()
        except (urllib.error.URLError, OSError) as e:
            return 502, json.dumps({"error": {"message": f"upstream unreachable: {e}", "code": 502}}).encode()


def _bare_turn(model: str, n: int) -> Any:
    """The little of a request that ``personas.text_completion`` reads (model, request number)."""
    from .personas import Turn

    return Turn(body={}, D=0, answer=[], rng=random.Random(0), n=n, model=model, document=True)


class _QuietServer(http.server.ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request: Any, client_address: Any) -> None:
        pass  # hung-up sockets are the point of this server, not errors worth a traceback


class FaultServer:
    """The server in a background thread. A context manager; ``base_url`` ends in ``/v1``."""

    def __init__(self, config: FaultConfig | None = None, *, port: int = 0) -> None:
        self.config = config or FaultConfig()
        self.config.validate()
        self._state = _State(self.config, random.Random(self.config.seed))
        handler = type("FaultHandler", (_Handler,), {"state": self._state})
        self._server = _QuietServer(("127.0.0.1", port), handler)
        self._threads: list[threading.Thread] = []
        self.port = int(self._server.server_address[1])
        self.base_url = f"http://127.0.0.1:{self.port}/v1"

    def start(self) -> FaultServer:
        """Serve in a daemon thread, with a watchdog that stops the server after ``max_seconds``; returns self."""
        serve = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        watch = threading.Thread(target=self._watchdog, daemon=True)
        self._threads = [serve, watch]
        for t in self._threads:
            t.start()
        return self

    def _watchdog(self) -> None:
        """Stop when the time or request budget is spent (a stalled test never hangs on us)."""
        self._state.stop.wait(self.config.max_seconds)
        self._state.stop.set()
        self._server.shutdown()

    def wait(self) -> None:
        """Block until the server stops by itself (or ``stop`` is called)."""
        while not self._state.stop.wait(0.2):
            pass
        for t in self._threads:
            t.join(timeout=5)

    def stop(self) -> None:
        """Stop serving, wait for the threads (up to 5 s each) and close the socket."""
        self._state.stop.set()
        for t in self._threads:
            t.join(timeout=5)
        self._server.server_close()

    def stats(self) -> dict[str, Any]:
        """Counts so far: requests, passed, injected (by kind) and injected_total, personas (replies by
        persona), most_in_flight (the most completions requests in flight at once: read, not yet
        answered), most_served (the most served at once: holding a slot of ``concurrency``, in their
        latency or being answered; at most ``concurrency``), elapsed_s (seconds since the server was
        made); the body of ``GET /stats``."""
        return self._state.stats()

    def release(self) -> None:
        """End the hold of ``hold_after``: the held requests and every later one are answered as usual
        (as ``POST /release`` does)."""
        self._state.released.set()

    def received(self) -> list[bytes]:
        """Every request received so far with ``record`` on, in arrival order, byte for byte: the
        request line, the headers, a blank line and the body (``GET /stats`` and ``POST /release``,
        the server's own routes, are not kept)."""
        with self._state.lock:
            return list(self._state.received)

    def answers(self) -> list[tuple[int, str, list[float]]]:
        """(request number, persona or fault kind, vector) of every new vector a reply proposed, in
        order: the personas' and plain answers, and the usable bad answers (huge, reasoning_only)."""
        with self._state.lock:
            return list(self._state.answers)

    def __enter__(self) -> FaultServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _kinds(text: str) -> tuple[str, ...]:
    if text in ("all", ""):
        return ALL_KINDS
    if text == "transport":
        return TRANSPORT_KINDS
    if text == "answers":
        return ANSWER_KINDS
    return tuple(k.strip() for k in text.split(",") if k.strip())


def _burst(text: str) -> tuple[int, int]:
    first, sep, last = text.partition("-")
    try:
        return (int(first), int(last)) if sep else (int(first), int(first))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected FIRST-LAST (request numbers), got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    """The command line (see the module docstring): serve until the budget is spent, SIGTERM or Ctrl-C.

    Prints ``listening URL`` first and the stats as JSON at the end; ``--answers-file`` gets the
    proposed vectors, ``--requests-file`` the requests received. Returns 0, or 2 for bad settings or a port that cannot be bound (one line on
    stderr); argparse exits 2 itself on a malformed flag.
    """
    p = argparse.ArgumentParser(prog="python -m ppprops.testing.fault_server", description=__doc__.splitlines()[0])
    p.add_argument("--port", type=int, default=0, help="0 = any free port (printed)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--upstream", default=None, help="OpenAI-compatible base URL to pass healthy requests to")
    src.add_argument("--synthetic", action="store_true", help="answer healthy requests with random vectors (default)")
    p.add_argument("--fault-rate", type=float, default=0.3)
    p.add_argument("--kinds", default="all", help="all | transport | answers | comma-separated kinds")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--retry-after", type=float, default=1.0, help="Retry-After of injected 429s, seconds")
    p.add_argument("--timeout-delay", type=float, default=2.0, help="how long a 'timeout' stalls, seconds")
    p.add_argument("--delay-max", type=float, default=0.3, help="longest 'delay', seconds")
    p.add_argument("--dim", type=int, default=None, help="D when a request does not tell")
    p.add_argument("--max-requests", type=int, default=None)
    p.add_argument("--max-seconds", type=float, default=600.0)
    p.add_argument("--personas", default="",
                   help=f"all (those of personas.PERSONAS) | comma-separated, from {', '.join(KNOWN_PERSONAS)}")
    p.add_argument("--v1-only", action="store_true", help="404 for any path but /v1/chat/completions and /v1/completions")
    p.add_argument("--error-body-code", type=int, default=502, help="code inside an injected error_body fault")
    p.add_argument("--answers-file", type=str, default=None, help="write the proposed vectors here as JSON when stopping")
    p.add_argument("--fixed-status", type=int, default=None,
                   help="answer every request that gets no fault with this HTTP status and --fixed-body")
    p.add_argument("--fixed-body", default="{}", help="the JSON body of those answers (with --fixed-status)")
    p.add_argument("--hold-after", type=int, default=None, metavar="N",
                   help="hold the requests after the first N open, unanswered, until POST /release (then answered as "
                        "usual) or the server stops (then dropped)")
    p.add_argument("--burst", type=_burst, default=None, metavar="FIRST-LAST",
                   help="requests FIRST to LAST (numbered from 1) always get a fault, the others at --fault-rate")
    p.add_argument("--latency", type=float, default=0.0, help="seconds every completions request takes before its answer")
    p.add_argument("--concurrency", type=int, default=None, help="the most completions requests served at once (default: all)")
    p.add_argument("--requests-file", type=str, default=None,
                   help="write every request received (request line, headers, body; UTF-8) here as a JSON list when stopping")
    a = p.parse_args(argv)
    cfg = FaultConfig(
        fault_rate=a.fault_rate, kinds=_kinds(a.kinds), seed=a.seed, upstream=a.upstream, delay_max_s=a.delay_max,
        timeout_s=a.timeout_delay, retry_after_s=a.retry_after, max_requests=a.max_requests, max_seconds=a.max_seconds,
        default_dim=a.dim, v1_only=a.v1_only, error_body_code=a.error_body_code, fixed_status=a.fixed_status,
        fixed_body=a.fixed_body, hold_after=a.hold_after, record=a.requests_file is not None, burst=a.burst,
        latency_s=a.latency, concurrency=a.concurrency,
        personas=tuple(PERSONAS) if a.personas == "all" else tuple(x.strip() for x in a.personas.split(",") if x.strip()),
    )
    try:
        server = FaultServer(cfg, port=a.port)
    except (ValueError, OSError) as e:
        print(f"fault_server: error: {e}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: server._state.stop.set())
    server.start()
    print(f"listening {server.base_url}", flush=True)
    try:
        server.wait()
    except KeyboardInterrupt:
        pass
    server.stop()
    if a.answers_file:
        with open(a.answers_file, "w", encoding="utf-8") as f:
            json.dump([{"request": n, "by": who, "params": v} for n, who, v in server.answers()], f)
    if a.requests_file:
        with open(a.requests_file, "w", encoding="utf-8") as f:
            json.dump([r.decode("utf-8", "replace") for r in server.received()], f)
    print(json.dumps(server.stats()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
