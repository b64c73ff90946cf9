"""How to reach the model: the LLM endpoint's settings (``LLMConfig``), part of every run's config.

The LLM client (``ppprops.llm.client``) takes these and nothing else of a run's settings.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import BeforeValidator, Field, model_validator
from pydantic.dataclasses import dataclass

from ..errors import ConfigError
from ..schema import SCHEMA, Flag, Float, Int, one_line_errors, parse_box


def parse_price(value: Any) -> tuple[float, float] | None:
    """``"IN,OUT"`` (the flag's form), ``[IN, OUT]`` (a file's) or a pair, as two floats; None stays None.

    Raises:
        ValueError: anything else.
    """
    if value is None:
        return None
    try:
        return parse_box(value)
    except ValueError:
        raise ValueError(f"expected IN,OUT (dollars per million prompt, completion tokens), got {value!r}") from None


MAX_TRANSPORT_RETRIES = 20
MAX_DELAY_S = 3600.0
REASONING_EFFORTS = ("none", "minimal", "low", "medium", "high")
STRUCTURED = ("auto", "json_schema", "grammar", "none")


@one_line_errors
@dataclass(frozen=True, config=SCHEMA)
class LLMConfig:
    """How to reach the model. No ``base_url`` means: start the embedded llama.cpp server.

    Raises:
        ConfigError: on construction, for a value out of range, a URL without http(s)://, a
            ``base_url`` without ``model``, or ``retry_max_s < retry_base_s``.
    """

    base_url: Annotated[str | None, Flag(
        "OpenAI-compatible API root that /chat/completions (/completions: document form) is appended to, "
        "e.g. http://localhost:11434/v1")] = None
    model: Annotated[str | None, Flag("model name at that endpoint (required with --base-url)")] = None
    # the name of the env var holding the key; the key itself is never stored
    api_key_env: Annotated[str | None, Flag("environment variable that holds the API key (never stored)", metavar="VAR")] = None
    # None: the prompt form's default (1.0 in the chat form; the document form: wire.document.TEMPERATURES)
    temperature: Annotated[Float | None, Field(ge=0.0, le=2.0), Flag(
        "sampling temperature, 0 to 2", range_text="[0, 2]",
        default_text="1.0 for the chat form; the document form alternates 0.6 and 1.0")] = None
    # None: enough for D numbers, plus room for reasoning (ppprops.llm.client.default_max_tokens)
    max_tokens: Annotated[Int | None, Field(ge=1), Flag(
        "answer token budget; reasoning counts against it (default: room for D numbers, plus room for reasoning "
        "when --reasoning-effort is set or the endpoint reasons)", default_text="")] = None
    timeout_s: Annotated[Float, Field(gt=0.0), Flag("seconds per request", name="timeout")] = 300.0
    # gpt-oss and OpenAI's take minimal|low|medium|high; "none" turns thinking off on Ollama's /v1
    reasoning_effort: Annotated[Literal["none", "minimal", "low", "medium", "high"] | None, Flag(
        "for reasoning models (gpt-oss, OpenAI o-series); none turns thinking off on Ollama's /v1")] = None
    structured: Annotated[Literal["auto", "json_schema", "grammar", "none"], Flag(
        "constrained output: auto = grammar for the embedded model, JSON schema otherwise")] = "auto"
    # extra tries of one request after a timeout, dropped connection, 429 or 5xx
    transport_retries: Annotated[Int, Field(ge=0, le=MAX_TRANSPORT_RETRIES), Flag(
        "retries of one request after a timeout, refused or dropped connection, 429 or 5xx", name="retries",
        range_text=f"[0, {MAX_TRANSPORT_RETRIES}]")] = 4
    context_size: Annotated[Int, Field(ge=512), Flag("embedded model context")] = 16384
    retry_base_s: Annotated[Float, Field(ge=0.0, le=MAX_DELAY_S), Flag(
        "first backoff in seconds, doubled per retry, with jitter", name="retry-base-delay", metavar="S",
        range_text=f"[0, {MAX_DELAY_S:g}] seconds")] = 1.0
    retry_max_s: Annotated[Float, Field(ge=0.0, le=MAX_DELAY_S), Flag(
        "longest backoff in seconds", name="retry-max-delay", metavar="S", range_text=f"[0, {MAX_DELAY_S:g}] seconds")] = 30.0
    retry_after_cap_s: Annotated[Float, Field(ge=0.0, le=MAX_DELAY_S), Flag(
        "longest Retry-After of a 429 that is honoured, seconds", name="retry-after-cap", metavar="S",
        range_text=f"[0, {MAX_DELAY_S:g}] seconds")] = 60.0
    # dollars per million prompt and completion tokens: what `show` prices the search's tokens at (ppprops.usage); never sent
    price: Annotated[tuple[float, float] | None, BeforeValidator(parse_price), Flag(
        "dollars per million prompt and completion tokens, e.g. 0.15,0.60: show gives the search's cost", metavar="IN,OUT",
        default_text="none")] = None

    @model_validator(mode="after")
    def _consistent(self) -> LLMConfig:
        if self.price is not None and not all(math.isfinite(p) and p >= 0 for p in self.price):
            raise ConfigError(f"--price must be two finite numbers >= 0 (dollars per million prompt, completion tokens), got "
                              f"{self.price[0]:g},{self.price[1]:g}")  # fmt: skip
        if self.retry_max_s < self.retry_base_s:
            raise ConfigError(f"--retry-max-delay ({self.retry_max_s}) must be >= --retry-base-delay ({self.retry_base_s})")
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ConfigError(f"--base-url must start with http:// or https://, got {self.base_url!r}")
        if self.base_url is not None:
            parts = urlsplit(self.base_url)
            try:
                port = parts.port
            except ValueError:
                port = 0
            if not parts.hostname or port == 0:
                what = "names no host" if not parts.hostname else "has a port outside 1-65535"
                raise ConfigError(f"--base-url {what}: {self.base_url!r}")
        if self.base_url is not None and not self.model:
            raise ConfigError("--model is required with --base-url")
        return self

    def validate(self) -> None:
        """Check again (construction already did): raises ConfigError naming the flag."""
        LLMConfig(**asdict(self))

    @property
    def embedded(self) -> bool:
        """True when the run starts the embedded llama.cpp server (no ``base_url``)."""
        return self.base_url is None
