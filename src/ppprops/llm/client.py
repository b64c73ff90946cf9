"""A thin chat-completions client over the official ``openai`` SDK that records every exchange.

Only the request body is recorded (never headers, so never the API key). Transport faults
(timeouts, refused connections, 429 with Retry-After, 5xx) are retried by the SDK's own bounded
exponential backoff; what is left after that surfaces as ``LLMError``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
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
        self._client = OpenAI(
            base_url=base_url, api_key=api_key, timeout=config.timeout_s, max_retries=config.transport_retries
        )

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
        import openai

        body = self.body(messages, D=D, seed=seed)
        request = json.dumps(body)
        prompt_chars = sum(len(m["content"]) for m in messages)
        sdk_args = {k: v for k, v in body.items() if k != "grammar"}
        extra = {"grammar": body["grammar"]} if "grammar" in body else None
        t0 = time.perf_counter()
        try:
            raw = self._client.chat.completions.with_raw_response.create(**sdk_args, extra_body=extra)
            latency = time.perf_counter() - t0
            completion = raw.parse()
        except openai.BadRequestError as e:
            if self.structured == "json_schema" and self.config.structured == "auto":
                # The endpoint does not take JSON-schema output: go on with plain answers.
                self.structured = "none"
                return self.complete(messages, D=D, seed=seed)
            return Exchange(request, _body_text(e), None, None, prompt_chars, None, None, time.perf_counter() - t0, False, f"bad_request: {e.status_code}")
        except (openai.APIConnectionError, openai.APITimeoutError, openai.RateLimitError, openai.InternalServerError) as e:
            raise LLMError(f"LLM endpoint failed after {self.config.transport_retries} retries: {e.__class__.__name__}") from e
        except openai.APIStatusError as e:
            raise LLMError(f"LLM endpoint answered HTTP {e.status_code}: {_short(e)}") from e
        choice = completion.choices[0] if completion.choices else None
        message = choice.message if choice else None
        content = message.content if message else None
        extra_fields = (message.model_extra or {}) if message else {}
        reasoning = extra_fields.get("reasoning_content") or extra_fields.get("reasoning")
        usage = completion.usage
        return Exchange(
            request=request,
            response=raw.http_response.text,
            content=content,
            reasoning=reasoning if isinstance(reasoning, str) else None,
            prompt_chars=prompt_chars,
            prompt_tokens=usage.prompt_tokens if usage else None,
            completion_tokens=usage.completion_tokens if usage else None,
            latency_s=latency,
            ok=True,
        )

    def close(self) -> None:
        self._client.close()


def _body_text(e: Exception) -> str | None:
    resp = getattr(e, "response", None)
    return getattr(resp, "text", None)


def _short(e: Exception) -> str:
    text = str(e).splitlines()[0] if str(e) else e.__class__.__name__
    return text[:200]
