"""Run settings, validated in one place and stored with the run."""

from __future__ import annotations

import argparse
import difflib
import json
import math
import tomllib
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .errors import ConfigError
from .methods import Mechanisms

# Sane upper bounds: past these a typo is far likelier than intent, and a run would not finish.
MAX_WARMUP = 10_000
MAX_ITERATIONS = 100_000
MAX_EPISODES = 10_000
MAX_PARSE_RETRIES = 10
MAX_TRANSPORT_RETRIES = 20
MAX_DELAY_S = 3600.0
ON_LLM_FAILURE = ("stop", "skip")
PROMPT_PARAMS = ("list", "indexed")  # see ppprops.wire.prompt.PARAMS_STYLES
PROMPT_LAYOUTS = ("static-first", "history-first")
PROMPT_FORMS = ("auto", "chat", "document")  # see RunConfig.form
# Default significant digits of a parameter per prompt form: the document form's labelled lists need
# the room (Ant-Ultra's K=10 prompt stays under 8,000 characters) and the small model gains nothing
# from a third digit; the chat form keeps the list form's 3.
PARAM_DIGITS = {"chat": 3, "document": 2}
REASONING_EFFORTS = ("none", "minimal", "low", "medium", "high")


@dataclass(frozen=True)
class LLMConfig:
    """How to reach the model. No base_url means: start the embedded llama.cpp server."""

    base_url: str | None = None
    model: str | None = None
    api_key_env: str | None = None  # name of the env var holding the key; the key itself is never stored
    temperature: float | None = None  # None: the prompt form's default (1.0 chat; document: wire.document.TEMPERATURES)
    max_tokens: int | None = None  # None: enough for D numbers, plus room for reasoning (ppprops.llm.client.default_max_tokens)
    timeout_s: float = 300.0
    # for reasoning models: gpt-oss and OpenAI's take minimal|low|medium|high; "none" turns thinking off on Ollama's /v1
    reasoning_effort: str | None = None
    structured: str = "auto"  # auto | json_schema | grammar | none
    transport_retries: int = 4  # extra tries of one request after a timeout, dropped connection, 429 or 5xx
    context_size: int = 16384  # embedded server only
    retry_base_s: float = 1.0  # first backoff; doubles per retry, with jitter
    retry_max_s: float = 30.0  # longest backoff between two tries
    retry_after_cap_s: float = 60.0  # a server's Retry-After is honoured up to this

    def validate(self) -> None:
        if self.temperature is not None and not (0.0 <= self.temperature <= 2.0):
            raise ConfigError(f"--temperature must be in [0, 2], got {self.temperature}")
        if self.max_tokens is not None and self.max_tokens < 1:
            raise ConfigError(f"--max-tokens must be >= 1, got {self.max_tokens}")
        if not (self.timeout_s > 0):
            raise ConfigError(f"--timeout must be > 0, got {self.timeout_s}")
        if self.structured not in ("auto", "json_schema", "grammar", "none"):
            raise ConfigError(f"--structured must be auto, json_schema, grammar or none, got {self.structured!r}")
        if self.reasoning_effort not in (None, *REASONING_EFFORTS):
            raise ConfigError(f"--reasoning-effort must be one of {', '.join(REASONING_EFFORTS)}, got {self.reasoning_effort!r}")
        if not (0 <= self.transport_retries <= MAX_TRANSPORT_RETRIES):
            raise ConfigError(f"--retries must be in [0, {MAX_TRANSPORT_RETRIES}], got {self.transport_retries}")
        for flag, v in (("--retry-base-delay", self.retry_base_s), ("--retry-max-delay", self.retry_max_s),
                        ("--retry-after-cap", self.retry_after_cap_s)):
            if not (math.isfinite(v) and 0 <= v <= MAX_DELAY_S):
                raise ConfigError(f"{flag} must be in [0, {MAX_DELAY_S:g}] seconds, got {v}")
        if self.retry_max_s < self.retry_base_s:
            raise ConfigError(f"--retry-max-delay ({self.retry_max_s}) must be >= --retry-base-delay ({self.retry_base_s})")
        if self.context_size < 512:
            raise ConfigError(f"--context-size must be >= 512, got {self.context_size}")
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
    on_llm_failure: str = "stop"  # stop (resumable) | skip (record a fallback candidate and go on)
    workers: int = 1  # processes that run episodes in parallel (results identical to serial)
    components: tuple[str, ...] = ()  # runs stored before task_spec existed: a generic task's component info keys
    diagnostics: tuple[str, ...] = ()  # the same, for diagnostics
    prompt_params: str = "list"  # how history parameters are written: list | indexed (ProPS form)
    # list form: significant digits per parameter (at most `decimals` decimals); 0: fixed decimals;
    # None: the prompt form's default (PARAM_DIGITS: 3 for chat, 2 for the document form)
    param_digits: int | None = None
    prompt_layout: str = "static-first"  # fixed sections before the history (prefix-cache friendly) | history-first
    # The task's whole declaration (ppprops.tasks.spec.TaskSpec.to_json()): env recipe, observation
    # adapter, feedback keys, prose. Stored with every run, so any process rebuilds the task from it;
    # None in a config built from a task name (the run stores the declaration when it starts).
    task_spec: dict[str, Any] | None = None
    # chat: the paper's instruction prompt (/chat/completions); document: the history as a document for a
    # base model to continue (/completions, wire.document); auto: document for the embedded model, chat otherwise
    prompt_form: str = "auto"

    def digits(self, form: str | None = None) -> int:
        """Significant digits of a parameter in the prompt of ``form`` (default: this run's form)."""
        return self.param_digits if self.param_digits is not None else PARAM_DIGITS[form or self.form]

    @property
    def form(self) -> str:
        """The prompt form this run uses: ``chat`` or ``document`` (``auto`` resolved). R2PO always chats."""
        if self.prompt_form == "auto":
            return "document" if self.llm.embedded and self.method != "r2po" else "chat"
        return self.prompt_form

    def validate(self) -> None:
        checks = [
            (self.warmup >= 1, f"--warmup must be >= 1 (the history starts from it), got {self.warmup}"),
            (self.warmup <= MAX_WARMUP, f"--warmup must be <= {MAX_WARMUP}, got {self.warmup}"),
            (self.iterations >= 0, f"--iterations must be >= 0, got {self.iterations}"),
            (self.iterations <= MAX_ITERATIONS, f"--iterations must be <= {MAX_ITERATIONS}, got {self.iterations}"),
            (self.top_k >= 0, f"--top-k must be >= 0 (0 keeps every entry), got {self.top_k}"),
            (self.episodes >= 1, f"--episodes must be >= 1, got {self.episodes}"),
            (self.episodes <= MAX_EPISODES, f"--episodes must be <= {MAX_EPISODES}, got {self.episodes}"),
            (self.final_episodes >= 0, f"--final-episodes must be >= 0, got {self.final_episodes}"),
            (self.final_episodes <= MAX_EPISODES, f"--final-episodes must be <= {MAX_EPISODES}, got {self.final_episodes}"),
            (0 <= self.seed < 2**63, f"--seed must be in [0, 2^63), got {self.seed}"),
            (0 <= self.decimals <= 8, f"--decimals must be in [0, 8], got {self.decimals}"),
            (self.parse_retries >= 0, f"--parse-retries must be >= 0, got {self.parse_retries}"),
            (self.parse_retries <= MAX_PARSE_RETRIES,
             f"--parse-retries must be <= {MAX_PARSE_RETRIES}, got {self.parse_retries}"),
            (1 <= self.workers <= 256, f"--workers must be in [1, 256], got {self.workers}"),
            (self.on_llm_failure in ON_LLM_FAILURE, f"--on-llm-failure must be stop or skip, got {self.on_llm_failure!r}"),
            (self.param_digits is None or 0 <= self.param_digits <= 8, f"--param-digits must be in [0, 8], got {self.param_digits}"),
            (self.prompt_params in PROMPT_PARAMS, f"--prompt-params must be list or indexed, got {self.prompt_params!r}"),
            (self.prompt_layout in PROMPT_LAYOUTS,
             f"--prompt-layout must be static-first or history-first, got {self.prompt_layout!r}"),
            (self.prompt_form in PROMPT_FORMS, f"--prompt-form must be auto, chat or document, got {self.prompt_form!r}"),
            (not (self.method == "r2po" and self.prompt_form == "document"),
             "--prompt-form document does not apply to r2po (its critic is a chat prompt); use auto or chat"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)
        from .methods import get_method

        get_method(self.method).check(self)  # what this method refuses (e.g. prompt switches for a black box)
        lo, hi = self.box
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"--box must be two finite numbers LOW < HIGH, got {lo}, {hi}")
        self.llm.validate()

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["box"] = list(self.box)
        if self.task_spec is None:
            del d["task_spec"]  # a config naming its task matches the stored one that holds the declaration
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> RunConfig:
        d = dict(d)
        d["mechanisms"] = Mechanisms.from_json(d["mechanisms"])
        d["llm"] = LLMConfig(**d["llm"])
        d["box"] = tuple(d["box"])
        for key in ("components", "diagnostics"):
            d[key] = tuple(d.get(key, ()))
        d.setdefault("prompt_form", "chat")  # runs stored before the document form existed chatted
        return cls(**d)

    def make_task(self):  # type: ignore[no-untyped-def]  # -> Task; imported late (tasks pull in gymnasium)
        """The task this run searches: from its stored declaration, else by name (older runs, fresh configs)."""
        from .tasks import generic_task, get_task, task_from_json

        if self.task_spec is not None:
            return task_from_json(self.task_spec)
        if self.components or self.diagnostics:
            return generic_task(self.task, self.components, self.diagnostics)
        return get_task(self.task)


def read_text(path: Path, what: str = "config file") -> str:
    """A user-named text file; a missing or unreadable one is one ConfigError line."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{what} {path} cannot be read ({e.__class__.__name__})") from None


def read_toml(path: Path) -> dict[str, Any]:
    """A TOML file as a table; every way it can fail is one ConfigError line."""
    path = Path(path)
    text = read_text(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML: {str(e).splitlines()[0]}") from None


def defaults_from_file(path: Path, actions: Iterable[argparse.Action], *, skip: Iterable[str] = ()) -> dict[str, Any]:
    """Turn a TOML file whose keys mirror command-line flags into argparse defaults (dest -> value).

    A key is a flag's long name without dashes (``top-k``) or its dest (``top_k``). Values are
    checked against the flag's type and choices here, because argparse checks neither for defaults.
    """
    raw = read_toml(path)
    by_key: dict[str, argparse.Action] = {}
    for act in actions:
        if act.dest in skip or act.dest == "help" or not act.option_strings:
            continue
        for opt in act.option_strings:
            if opt.startswith("--"):
                by_key[opt[2:]] = act
        by_key[act.dest] = act
    out: dict[str, Any] = {}
    for key, value in raw.items():
        act = by_key.get(key)
        if act is None:
            names = sorted(k for k in by_key if "_" not in k)
            close = difflib.get_close_matches(key.replace("_", "-"), names, n=1)
            hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(names)}"
            raise ConfigError(f"config file {path}: unknown key {key!r} ({hint})")
        out[act.dest] = file_value(path, key, value, act)
    return out


def file_value(path: Path, key: str, value: Any, act: argparse.Action) -> Any:
    """A file's ``key = value`` as the parsed value of the flag ``act``, checked as the command
    line would check it (type, choices, on/off, lists); ``path`` only names the file in errors.
    Raises ConfigError."""
    bad = ConfigError(f"config file {path}: {key} = {value!r} is not a valid value")
    conv = act.type
    if act.nargs == 0:  # store_true
        if not isinstance(value, bool):
            raise ConfigError(f"config file {path}: {key} must be true or false, got {value!r}")
        return value
    if isinstance(value, dict) and getattr(conv, "accepts_table", False):
        value = json.dumps(value)  # e.g. env-kwargs = { g = 9.81 }: the flag's JSON text
    elif isinstance(value, dict):
        raise bad
    if isinstance(act, argparse._AppendAction):  # a repeatable flag: a list of strings
        if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise ConfigError(f"config file {path}: {key} must be a list of strings, got {value!r}")
        return [v if conv is None else conv(v) for v in value]
    if isinstance(value, list):  # a box: [low, high]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise bad
        value = ",".join(str(v) for v in value)
    if conv is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config file {path}: {key} must be an integer, got {value!r}")
    elif conv is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config file {path}: {key} must be a number, got {value!r}")
        value = float(value)
    elif isinstance(value, bool):
        value = "on" if value else "off"  # on|off flags
    if conv is not None and conv not in (int, float):
        try:
            value = conv(str(value))
        except (argparse.ArgumentTypeError, TypeError, ValueError) as e:
            raise ConfigError(f"config file {path}: {key}: {e}") from None
    elif conv is None and not isinstance(value, str):
        raise ConfigError(f"config file {path}: {key} must be a string, got {value!r}")
    if act.choices is not None and value not in act.choices:
        raise ConfigError(f"config file {path}: {key} must be one of {', '.join(map(str, act.choices))}, got {value!r}")
    return value
