"""Run settings, validated in one place and stored with the run."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from .errors import ConfigError
from .methods import Mechanisms


@dataclass(frozen=True)
class LLMConfig:
    """How to reach the model. No base_url means: start the embedded llama.cpp server."""

    base_url: str | None = None
    model: str | None = None
    api_key_env: str | None = None  # name of the env var holding the key; the key itself is never stored
    temperature: float = 1.0
    max_tokens: int | None = None  # None: enough for D numbers (see ppprops.llm.client)
    timeout_s: float = 300.0
    reasoning_effort: str | None = None  # for reasoning models such as gpt-oss ("low", "medium", "high")
    structured: str = "auto"  # auto | json_schema | grammar | none
    transport_retries: int = 4
    context_size: int = 16384  # embedded server only

    def validate(self) -> None:
        if not (0.0 <= self.temperature <= 2.0):
            raise ConfigError(f"--temperature must be in [0, 2], got {self.temperature}")
        if self.max_tokens is not None and self.max_tokens < 1:
            raise ConfigError(f"--max-tokens must be >= 1, got {self.max_tokens}")
        if not (self.timeout_s > 0):
            raise ConfigError(f"--timeout must be > 0, got {self.timeout_s}")
        if self.structured not in ("auto", "json_schema", "grammar", "none"):
            raise ConfigError(f"--structured must be auto, json_schema, grammar or none, got {self.structured!r}")
        if self.reasoning_effort not in (None, "minimal", "low", "medium", "high"):
            raise ConfigError(f"--reasoning-effort must be minimal, low, medium or high, got {self.reasoning_effort!r}")
        if self.transport_retries < 0:
            raise ConfigError(f"transport retries must be >= 0, got {self.transport_retries}")
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ConfigError(f"--base-url must start with http:// or https://, got {self.base_url!r}")
        if self.base_url is not None and not self.model:
            raise ConfigError("--model is required with --base-url")

    @property
    def embedded(self) -> bool:
        return self.base_url is None


@dataclass(frozen=True)
class RunConfig:
    task: str
    method: str
    mechanisms: Mechanisms
    warmup: int = 10
    iterations: int = 50
    top_k: int = 10
    episodes: int = 1
    final_episodes: int = 20
    seed: int = 0
    box: tuple[float, float] = (-6.0, 6.0)
    decimals: int = 2
    parse_retries: int = 2  # extra asks with a correction before falling back
    llm: LLMConfig = field(default_factory=LLMConfig)

    def validate(self) -> None:
        checks = [
            (self.warmup >= 1, f"--warmup must be >= 1 (the history starts from it), got {self.warmup}"),
            (self.iterations >= 0, f"--iterations must be >= 0, got {self.iterations}"),
            (self.top_k >= 0, f"--top-k must be >= 0 (0 keeps every entry), got {self.top_k}"),
            (self.episodes >= 1, f"--episodes must be >= 1, got {self.episodes}"),
            (self.final_episodes >= 0, f"--final-episodes must be >= 0, got {self.final_episodes}"),
            (0 <= self.seed < 2**63, f"--seed must be in [0, 2^63), got {self.seed}"),
            (0 <= self.decimals <= 8, f"--decimals must be in [0, 8], got {self.decimals}"),
            (self.parse_retries >= 0, f"parse retries must be >= 0, got {self.parse_retries}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)
        lo, hi = self.box
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"--box must be two finite numbers LOW < HIGH, got {lo}, {hi}")
        self.llm.validate()

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["box"] = list(self.box)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> RunConfig:
        d = dict(d)
        d["mechanisms"] = Mechanisms.from_json(d["mechanisms"])
        d["llm"] = LLMConfig(**d["llm"])
        d["box"] = tuple(d["box"])
        return cls(**d)
