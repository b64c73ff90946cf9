"""A thin chat-completions client over the official ``openai`` SDK that records every exchange.

Only the request body is recorded (never headers, so never the API key). Transport faults
(timeouts, refused or dropped connections, 429, 5xx, a garbled body) are retried here, not in the
SDK (its ``max_retries`` is 0), so every try is counted and recorded: exponential backoff from
``retry_base_s`` with jitter, capped at ``retry_max_s``; a 429's Retry-After is honoured up to
``retry_after_cap_s``. Past ``transport_retries`` retries the request ends in ``LLMUnavailable``,
carrying the failed tries so the caller can record them.
"""

from __future__ import annotations

import email.utils
import json
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Protocol

from ..config import LLMConfig
from ..errors import LLMError


@dataclass(frozen=True)
class Exchange:
    """One HTTP round trip, as recorded in the store."""

    request: str  # the JSON body sent
    response: str | None  # the raw JSON body received
    content: str | None  # the assistant's final text
    reasoning: str | None  # reasoning text when the server returns it separately
    prompt_chars: int
    prompt_tokens: int | None
    completion_tokens: int | None
    latency_s: float
    ok: bool
    error: str | None = None
    error_kind: str | None = None  # timeout | refused | dropped | rate_limited | http_NNN | bad_response | bad_request
    retry: int = 0  # 0 for the first try of a request, n for its n-th transport retry
    answer_source: str | None = None  # set by the proposer: content | reasoning
    failures: tuple[Exchange, ...] = ()  # failed tries before this one (transport retries)


class LLMUnavailable(LLMError):
    """A request kept failing with transient faults past the retry bound. Carries the failed tries."""

    def __init__(self, message: str, failures: tuple[Exchange, ...]) -> None:
        super().__init__(message)
        self.failures = failures

    @property
    def kind(self) -> str:
        return (self.failures[-1].error_kind or "unknown") if self.failures else "unknown"


class LLMRejected(LLMUnavailable):
    """The endpoint refused the request for good (401, 403, 404, ...): retrying or skipping cannot help."""


class Chat(Protocol):
    """What a proposer needs from a model: one chat completion, recorded."""

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange: ...


def params_schema(D: int) -> dict[str, Any]:
    return {
        "type": "object",
        "properties": {"params": {"type": "array", "items": {"type": "number"}, "minItems": D, "maxItems": D}},
        "required": ["params"],
        "additionalProperties": False,
    }


def params_grammar(D: int) -> str:
    """GBNF for {"params":[n, ...]} with exactly D plain decimals and no free whitespace.

    llama.cpp's JSON-schema grammar lets small models pad with whitespace until max_tokens;
    this one cannot, which keeps answers short and always parseable.
    """
    rest = f' ("," ws num){{{D - 1}}}' if D > 1 else ""
    return (
        f'root ::= "{{\\"params\\": [" num{rest} "]}}"\n'
        'ws ::= " "?\n'
        'num ::= "-"? [0-9] [0-9]? [0-9]? ("." [0-9] [0-9]? [0-9]?)?\n'
    )


def default_max_tokens(D: int) -> int:
    """Room for D numbers plus the JSON frame. Some tokenizers (Gemma's) spend one token per
    digit, so "-12.99, " can take 7 tokens; 8 per number leaves a margin."""
    return 24 + 8 * D


class ChatClient:
    def __init__(self, config: LLMConfig, *, base_url: str, model: str, api_key: str, grammar_ok: bool) -> None:
        from openai import OpenAI

        self.config = config
        self.model = model
        self.structured = config.structured
        if self.structured == "auto":
            self.structured = "grammar" if grammar_ok else "json_schema"
        self._client = OpenAI(base_url=base_url, api_key=api_key, timeout=config.timeout_s, max_retries=0)
        self.sleep: Callable[[float], None] = time.sleep
        self._jitter = random.Random()

    def body(self, messages: list[dict[str, str]], *, D: int, seed: int | None) -> dict[str, Any]:
        body: dict[str, Any] = {
            "model": self.model,
            "messages": messages,
            "temperature": self.config.temperature,
            "max_tokens": self.config.max_tokens or default_max_tokens(D),
        }
        if seed is not None:
            body["seed"] = seed
        if self.config.reasoning_effort:
            body["reasoning_effort"] = self.config.reasoning_effort
        if self.structured == "json_schema":
            body["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "policy_parameters", "schema": params_schema(D), "strict": True},
            }
        elif self.structured == "grammar":
            body["grammar"] = params_grammar(D)
        return body

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        """One answer, after up to ``transport_retries`` retries of transient faults.

        Returns an ``ok`` exchange (or a non-retryable 400, ``ok`` False, for the caller's
        correction loop), with the failed tries in ``failures``. Raises ``LLMUnavailable``.
        """
        failures: list[Exchange] = []
        retries = self.config.transport_retries
        retry = 0
        while True:
            ex, retry_after = self._attempt(messages, D=D, seed=seed, retry=retry)
            if ex.ok:
                return replace(ex, failures=tuple(failures))
            if ex.error_kind == "bad_request":
                if self.structured == "json_schema" and self.config.structured == "auto":
                    # The endpoint does not take JSON-schema output: go on with plain answers.
                    self.structured = "none"
                    failures.append(ex)
                    continue
                return replace(ex, failures=tuple(failures))
            failures.append(ex)
            if not _retryable(ex.error_kind):
                raise LLMRejected(f"LLM endpoint refused the request: {ex.error}", tuple(failures))
            if retry >= retries:
                raise LLMUnavailable(
                    f"LLM endpoint failed {len(failures)} times in a row (last: {ex.error})", tuple(failures)
                )
            self.sleep(self.backoff(retry, retry_after))
            retry += 1

    def backoff(self, retry: int, retry_after: float | None) -> float:
        """Seconds to wait before retry ``retry + 1``: Retry-After (capped) if given, else
        exponential with "equal jitter" (half fixed, half random), so clients do not retry in step."""
        cfg = self.config
        if retry_after is not None:
            return min(max(retry_after, 0.0), cfg.retry_after_cap_s)
        d = min(cfg.retry_max_s, cfg.retry_base_s * (2.0**retry))
        return d / 2 + self._jitter.uniform(0.0, d / 2)

    def _attempt(self, messages: list[dict[str, str]], *, D: int, seed: int | None, retry: int) -> tuple[Exchange, float | None]:
        """One HTTP round trip, never raising for endpoint faults: (exchange, Retry-After seconds)."""
        import openai

        body = self.body(messages, D=D, seed=seed)
        request = json.dumps(body)
        prompt_chars = sum(len(m["content"]) for m in messages)
        sdk_args = {k: v for k, v in body.items() if k != "grammar"}
        extra = {"grammar": body["grammar"]} if "grammar" in body else None
        t0 = time.perf_counter()

        def failed(kind: str, error: str, response: str | None = None) -> Exchange:
            return Exchange(request, response, None, None, prompt_chars, None, None, time.perf_counter() - t0, False,
                            error, error_kind=kind, retry=retry)

        try:
            raw = self._client.chat.completions.with_raw_response.create(**sdk_args, extra_body=extra)
            latency = time.perf_counter() - t0
            text = raw.http_response.text
            completion = raw.parse()
            choices = completion.choices  # a garbled body may parse into something without them
        except openai.APITimeoutError:
            return failed("timeout", f"timeout: no answer within {self.config.timeout_s:g} s"), None
        except openai.APIConnectionError as e:
            kind = "refused" if _is_refused(e) else "dropped"
            return failed(kind, f"{kind}: {_cause(e)}"), None
        except openai.APIStatusError as e:
            code = e.status_code
            kind = "bad_request" if code == 400 else "rate_limited" if code == 429 else f"http_{code}"
            after = _retry_after(e)
            note = f" (Retry-After {after:g} s)" if after is not None else ""
            return failed(kind, f"{kind}: HTTP {code}{note}: {_short(e)}", _body_text(e)), after
        except Exception as e:  # a 200 whose body is not a chat completion (garbled, cut, not JSON)
            return failed("bad_response", f"bad_response: {e.__class__.__name__}: {_short(e)}"), None
        choice = choices[0] if choices else None
        message = choice.message if choice else None
        content = message.content if message else None
        extra_fields = (message.model_extra or {}) if message else {}
        reasoning = extra_fields.get("reasoning_content") or extra_fields.get("reasoning")
        usage = completion.usage
        return Exchange(
            request=request,
            response=text,
            content=content,
            reasoning=reasoning if isinstance(reasoning, str) else None,
            prompt_chars=prompt_chars,
            prompt_tokens=usage.prompt_tokens if usage else None,
            completion_tokens=usage.completion_tokens if usage else None,
            latency_s=latency,
            ok=True,
            retry=retry,
        ), None

    def close(self) -> None:
        self._client.close()


def _retryable(kind: str | None) -> bool:
    """Transient faults only: a 401, 403 or 404 will not heal by asking again."""
    if kind in ("timeout", "refused", "dropped", "rate_limited", "bad_response"):
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
