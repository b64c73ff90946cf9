"""Run settings: one schema, validated by pydantic, stored with the run.

``RunConfig`` (with its ``LLMConfig`` and the method's ``Mechanisms``) is what a run stores and
resumes from; ``TaskOptions`` is how a user names the task, which becomes the config's ``task`` and
``task_spec`` (the task's whole declaration). Every user-facing setting is a field of one of them
carrying a ``Flag``: its ``ppprops run`` flag, help text and error wording. ``ppprops.settings``
derives the command-line flags, the keys of config and experiment-spec files and the
one-line errors from these fields, so a setting is declared once, here.

Constructing any of these classes validates it (types, choices, bounds, and the checks that
involve several fields); a bad value is one ``ConfigError`` line naming the flag, e.g.
``--warmup must be >= 1 (the history starts from it), got 0``.
"""

from __future__ import annotations

import functools
import json
import math
import tomllib
from collections.abc import Callable, Collection, Mapping
from dataclasses import asdict
from dataclasses import dataclass as plain_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar

from pydantic import BeforeValidator, ConfigDict, Field, Strict, ValidationError, model_validator
from pydantic.dataclasses import dataclass

from .errors import ConfigError, MissingExtraError
from .methods import SWITCH_HELP, SWITCHES, Mechanisms, search_method_names, switch_flag

if TYPE_CHECKING:
    from .tasks import Task

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
STRUCTURED = ("auto", "json_schema", "grammar", "none")


@plain_dataclass(frozen=True)
class Flag:
    """How a schema field appears to a user: as ``--<name>`` on the command line and as a key
    (``name`` or ``name`` with underscores) in config and spec files.

    Attributes:
        help: the help text; ``(default X)`` is appended from the field's default.
        name: the flag without ``--`` when it is not the field name with dashes (``timeout`` for
            ``timeout_s``).
        metavar: argparse's placeholder for the value.
        range_text: bound errors say ``must be in <range_text>`` (``[0, 2]``) instead of naming
            the one bound that failed.
        hint: added to a bound error in parentheses (``the history starts from it``).
        default_text: the default as help shows it, when the field's own default does not say it.
        repeatable: a list given by repeating the flag (``--component a --component b``).
        choices: the allowed values, for a string field whose choices are known only at run time;
            a collection other than a list is lazy (``methods.MethodChoices``: the plugins' methods
            are listed when a name is not found), and the flag then shows ``metavar`` (default the
            key in capitals) instead of the choices, which only ``--help`` lists.
    """

    help: str
    name: str | None = None
    metavar: str | None = None
    range_text: str | None = None
    hint: str = ""
    default_text: str | None = None
    repeatable: bool = False
    choices: Callable[[], Collection[str]] | None = None


# -- values as users write them -------------------------------------------------------------------
def parse_box(value: Any) -> tuple[float, float]:
    """``"LOW,HIGH"`` (the flag's form), ``[LOW, HIGH]`` (a file's) or a pair, as two floats.

    Raises:
        ValueError: anything else.
    """
    if isinstance(value, str):
        try:
            lo, hi = (float(v) for v in value.split(","))
        except ValueError:
            raise ValueError(f"expected LOW,HIGH, got {value!r}") from None
        return lo, hi
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(_is_number(v) for v in value):
        return float(value[0]), float(value[1])
    raise ValueError(f"expected LOW,HIGH or [LOW, HIGH], got {value!r}")


def parse_on_off(value: Any) -> bool | None:
    """A switch: a bool, or ``on``/``off`` (also true/false, yes/no, 1/0); None stays None.

    Raises:
        ValueError: any other value.
    """
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, str):
        if value.lower() in ("on", "true", "yes", "1"):
            return True
        if value.lower() in ("off", "false", "no", "0"):
            return False
    raise ValueError(f"expected on or off, got {value!r}")


def parse_json_object(value: Any) -> dict[str, Any] | None:
    """A JSON object given as text (the flag's form) or as a table (a file's); None stays None.

    Raises:
        ValueError: text that is not a JSON object, or any other value.
    """
    if value is None or isinstance(value, dict):
        return value
    if isinstance(value, str):
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError as e:
            raise ValueError(f"expected a JSON object such as '{{\"g\": 9.81}}', got {value!r} ({e.msg})") from None
        if isinstance(parsed, dict):
            return parsed
    raise ValueError(f"expected a JSON object such as '{{\"g\": 9.81}}', got {value!r}")


def parse_names(value: Any) -> tuple[str, ...] | None:
    """``"K1,K2"`` (the flag's form) or a list of names (a file's); None stays None.

    Raises:
        ValueError: an empty list, or a value that is neither.
    """
    if value is None:
        return None
    if isinstance(value, str):
        names = tuple(n.strip() for n in value.split(",") if n.strip())
    elif isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        names = tuple(value)
    else:
        raise ValueError(f"expected K1,K2,..., got {value!r}")
    if not names:
        raise ValueError(f"expected K1,K2,..., got {value!r}")
    return names


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


Int = Annotated[int, Strict()]
Float = Annotated[float, Strict()]
Box = Annotated[tuple[float, float], BeforeValidator(parse_box)]
Names = Annotated[tuple[str, ...] | None, BeforeValidator(parse_names)]
JsonObject = Annotated[dict[str, Any] | None, BeforeValidator(parse_json_object)]
OnOff = Annotated[bool | None, BeforeValidator(parse_on_off)]

_SCHEMA = ConfigDict(extra="forbid", arbitrary_types_allowed=True)
_C = TypeVar("_C")


# -- one-line errors -------------------------------------------------------------------------------
def _flag_of(cls: type, name: str) -> str:
    info = flag_info(cls, name)
    return "--" + ((info.name if info is not None and info.name else name).replace("_", "-"))


def flag_info(cls: type, name: str) -> Flag | None:
    """The ``Flag`` of field ``name`` of a schema class, or None when it is not a user setting."""
    fields = getattr(cls, "__pydantic_fields__", {})
    if name not in fields:
        return None
    return next((m for m in fields[name].metadata if isinstance(m, Flag)), None)


def _shown(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def describe_error(err: Mapping[str, Any], name: str, info: Flag | None) -> str:
    """One pydantic error as the line a user reads; ``name`` is the flag or key the user gave."""
    kind, value, ctx = err["type"], err.get("input"), err.get("ctx") or {}
    if kind == "value_error" and isinstance(ctx.get("error"), ConfigError):
        return str(ctx["error"])  # a check of several fields, worded where it is made
    bounds = {"greater_than_equal": ">=", "greater_than": ">", "less_than_equal": "<=", "less_than": "<"}
    if kind in bounds:
        if info is not None and info.range_text:
            return f"{name} must be in {info.range_text}, got {_shown(value)}"
        limit = next(iter(ctx.values()))
        limit = int(limit) if isinstance(limit, float) and limit.is_integer() else limit
        hint = f" ({info.hint})" if info is not None and info.hint else ""
        return f"{name} must be {bounds[kind]} {limit}{hint}, got {_shown(value)}"
    if kind == "literal_error":
        allowed = ", ".join(v.strip("'") for v in str(ctx.get("expected", "")).replace(" or ", ", ").split(", "))
        return f"{name} must be one of {allowed}, got {_shown(value)}"
    if kind in ("int_type", "int_parsing", "int_from_float"):
        return f"{name} must be an integer, got {value!r}"
    if kind in ("float_type", "float_parsing"):
        return f"{name} must be a number, got {value!r}"
    if kind in ("bool_type", "bool_parsing"):
        return f"{name} must be true or false, got {value!r}"
    if kind == "string_type":
        return f"{name} must be a string, got {value!r}"
    if kind in ("tuple_type", "list_type"):
        return f"{name} must be a list of strings, got {value!r}"
    if kind == "missing":
        return f"{name} is required"
    if kind == "unexpected_keyword_argument":
        return f"unknown setting {name.lstrip('-').replace('-', '_')!r}"
    if kind == "value_error":
        return f"{name}: {ctx.get('error', err.get('msg'))}"
    return f"{name}: {err.get('msg')}, got {value!r}"


def config_error(cls: type, e: ValidationError) -> ConfigError:
    """The first error of a schema class's validation as one ConfigError line naming the flag."""
    err = e.errors()[0]
    owner: type = cls
    name = ""
    for part in err["loc"]:  # walk into nested schema classes (RunConfig.llm.timeout_s -> --timeout)
        if not isinstance(part, str):
            continue
        name = part
        nested = getattr(owner, "__pydantic_fields__", {}).get(part)
        annotation = getattr(nested, "annotation", None)
        if isinstance(annotation, type) and hasattr(annotation, "__dataclass_fields__"):
            owner = annotation
    if owner is Mechanisms and name in SWITCHES:
        return ConfigError(describe_error(err, switch_flag(name), None))
    return ConfigError(describe_error(err, _flag_of(owner, name) if name else owner.__name__, flag_info(owner, name)))


def one_line_errors(cls: type[_C]) -> type[_C]:
    """Make constructing ``cls`` (a pydantic dataclass) raise ``config_error`` instead of pydantic's
    multi-line ValidationError, so ``RunConfig(...)`` and ``dataclasses.replace`` fail in one line."""
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        try:
            init(self, *args, **kwargs)
        except ValidationError as e:
            raise config_error(cls, e) from None

    cls.__init__ = __init__  # type: ignore[method-assign]
    return cls


# -- the schema -----------------------------------------------------------------------------------
@one_line_errors
@dataclass(frozen=True, config=_SCHEMA)
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

    @model_validator(mode="after")
    def _consistent(self) -> LLMConfig:
        if self.retry_max_s < self.retry_base_s:
            raise ConfigError(f"--retry-max-delay ({self.retry_max_s}) must be >= --retry-base-delay ({self.retry_base_s})")
        if self.base_url is not None and not self.base_url.startswith(("http://", "https://")):
            raise ConfigError(f"--base-url must start with http:// or https://, got {self.base_url!r}")
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


@one_line_errors
@dataclass(frozen=True, config=_SCHEMA)
class RunConfig:
    """Everything that defines a run (paper Algorithm 1 and the settings of Sec. III), stored with it as JSON.

    A search evaluates ``warmup`` uniform samples in ``box``, then ``iterations`` proposals of
    ``method``, each on ``episodes`` seeded episodes, keeping the best ``top_k`` in the prompt
    (Eq. 9); the best candidate is then evaluated on ``final_episodes`` fresh seeds.

    Raises:
        ConfigError: on construction, for a value out of range (naming its flag), an empty or
            reversed ``box``, an unknown method, or mechanisms the method refuses.
    """

    task: str
    method: Annotated[str, Flag("a preset of the paper, R2PO, or a black-box baseline at the same budget",
                                choices=search_method_names)]
    mechanisms: Mechanisms
    warmup: Annotated[Int, Field(ge=1, le=MAX_WARMUP), Flag("random warm-up policies", hint="the history starts from it")] = 10
    iterations: Annotated[Int, Field(ge=0, le=MAX_ITERATIONS), Flag(
        "LLM iterations; r2po: LLM calls, two per two-stage iteration; random, cmaes: samples")] = 50
    top_k: Annotated[Int, Field(ge=0), Flag("history entries in the prompt; 0 = all", hint="0 keeps every entry")] = 10
    episodes: Annotated[Int, Field(ge=1, le=MAX_EPISODES), Flag("episodes per candidate", default_text="1; 20 for r2po")] = 1
    final_episodes: Annotated[Int, Field(ge=0, le=MAX_EPISODES), Flag("fresh episodes for the best policy")] = 20
    seed: Annotated[Int, Field(ge=0, lt=2**63), Flag("run seed: warm-up, episode seeds, LLM sampling seeds",
                                                      range_text="[0, 2^63)")] = 0
    box: Annotated[Box, Flag("feasible range of every parameter", metavar="LOW,HIGH", default_text="-6,6")] = (-6.0, 6.0)
    decimals: Annotated[Int, Field(ge=0, le=8), Flag("decimals of numbers in the prompt", range_text="[0, 8]")] = 2
    parse_retries: Annotated[Int, Field(ge=0, le=MAX_PARSE_RETRIES), Flag("corrections asked for before a fallback")] = 2
    llm: LLMConfig = Field(default_factory=LLMConfig)
    on_llm_failure: Annotated[Literal["stop", "skip"], Flag(
        "when the endpoint stays down past --retries: stop, resumable, or skip: record a fallback candidate and go on")] = "stop"
    workers: Annotated[Int, Field(ge=1, le=256), Flag("processes running episodes in parallel", range_text="[1, 256]")] = 1
    components: tuple[str, ...] = ()  # runs stored before task_spec existed: a generic task's component info keys
    diagnostics: tuple[str, ...] = ()  # the same, for diagnostics
    prompt_params: Annotated[Literal["list", "indexed"], Flag(
        "history parameters as one list (compact) or as ProPS-style params[i]: value pairs")] = "list"
    # None: the prompt form's default (PARAM_DIGITS: 3 for chat, 2 for the document form)
    param_digits: Annotated[Int | None, Field(ge=0, le=8), Flag(
        "significant digits of each parameter, at most --decimals decimals; 0 = fixed decimals",
        range_text="[0, 8]", default_text="3 in the chat form's list, 2 in the document form")] = None
    prompt_layout: Annotated[Literal["static-first", "history-first"], Flag(
        "fixed sections before the history (a server's prefix cache reuses them) or history first")] = "static-first"
    # chat: the paper's instruction prompt (/chat/completions); document: the history as a document for a
    # base model to continue (/completions, wire.document); auto: document for the embedded model, chat otherwise
    prompt_form: Annotated[Literal["auto", "chat", "document"], Flag(
        "chat: the paper's instruction prompt; document: the history as a document for a base model to continue "
        "(completions endpoint); auto: document for the embedded model, chat otherwise")] = "auto"
    # The task's whole declaration (ppprops.tasks.spec.TaskSpec.to_json()): env recipe, observation
    # adapter, feedback keys, prose. Stored with every run, so any process rebuilds the task from it;
    # None in a config built from a task name (the run stores the declaration when it starts).
    task_spec: dict[str, Any] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> RunConfig:
        from .methods import get_method

        lo, hi = self.box
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"--box must be two finite numbers LOW < HIGH, got {lo}, {hi}")
        get_method(self.method).check(self)  # what this method refuses (e.g. prompt switches for a black box)
        if self.method == "r2po" and self.prompt_form == "document":
            raise ConfigError("--prompt-form document does not apply to r2po (its critic is a chat prompt); use auto or chat")
        return self

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
        """Check again (construction already did): raises ConfigError naming the flag."""
        RunConfig.from_json(self.to_json())

    def to_json(self) -> dict[str, Any]:
        """The stored form: plain JSON types; no ``task_spec`` key when it is None."""
        d = asdict(self)
        d["box"] = list(self.box)
        if self.task_spec is None:
            del d["task_spec"]  # a config naming its task matches the stored one that holds the declaration
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RunConfig:
        """A stored config, of this version or an older one (keys added since take their defaults).

        Raises:
            ConfigError: a key this version does not know, or a value it refuses.
        """
        d = dict(d)
        d["mechanisms"] = Mechanisms.from_json(d["mechanisms"])
        d["llm"] = LLMConfig(**d.get("llm", {}))
        for key in ("box", "components", "diagnostics"):
            if key in d:
                d[key] = tuple(d[key])
        d.setdefault("prompt_form", "chat")  # runs stored before the document form existed chatted
        try:
            return cls(**d)
        except TypeError as e:  # an unknown key
            raise ConfigError(f"stored configuration: {e}") from None

    def make_task(self) -> Task:
        """The task this run searches: from its stored declaration, else by name (older runs, fresh configs)."""
        from .tasks import generic_task, get_task, task_from_json

        if self.task_spec is not None:
            return task_from_json(self.task_spec)
        if self.components or self.diagnostics:
            return generic_task(self.task, self.components, self.diagnostics)
        return get_task(self.task)


@one_line_errors
@dataclass(frozen=True, config=_SCHEMA)
class TaskOptions:
    """How a user names the task of a run: ``--env`` or ``--task-file``, and the options of a task
    that is not a paper task. ``load()`` turns them into the ``Task`` whose name and declaration
    (``task_spec``) the RunConfig stores.

    Raises:
        ConfigError: on construction, for a value of the wrong type.
    """

    env: Annotated[str | None, Flag(
        "task name (see `ppprops envs`), a Gymnasium id, module:EnvId, or module:attr (an env class or factory)")] = None
    task_file: Annotated[Path | None, Flag(
        "a task described in TOML (env, observation, feedback keys, prose; docs/own-robot.md) instead of --env",
        metavar="FILE")] = None
    env_kwargs: Annotated[JsonObject, Flag("keyword arguments of the env's constructor, as a JSON object", metavar="JSON")] = None
    max_episode_steps: Annotated[Int | None, Field(ge=1), Flag(
        "time limit of an episode (needed when the env has none of its own)", metavar="N")] = None
    gym_packages: Annotated[tuple[str, ...], Flag(
        "a module to import first, e.g. one that registers the env (repeatable)", metavar="MOD", repeatable=True)] = ()
    obs_keys: Annotated[Names, Flag("a Dict observation: the entries the policy sees, in this order", metavar="K1,K2")] = None
    components: Annotated[tuple[str, ...], Flag(
        "an info key to sum as a reward component (repeatable); KEY.SUB picks an entry of a dict, KEY.* all",
        name="component", metavar="KEY", repeatable=True)] = ()
    diagnostics: Annotated[tuple[str, ...], Flag(
        "an info key to report as a diagnostic (its last value; repeatable)", name="diagnostic", metavar="KEY",
        repeatable=True)] = ()

    def load(self) -> Task:
        """The task (``ppprops.tasks.load_task``).

        Raises:
            ConfigError: neither ``env`` nor ``task_file``, or the task cannot be made (an unknown
                id, a bad task file, a module that fails to import, an info key the env lacks).
        """
        if self.env is None and self.task_file is None:
            raise ConfigError("--env or --task-file is required (on the command line, or in the --config file)")
        from .tasks import load_task

        return load_task(self.env, task_file=self.task_file, env_kwargs=self.env_kwargs, max_episode_steps=self.max_episode_steps,
                         gym_packages=self.gym_packages, obs_keys=self.obs_keys, components=self.components,
                         diagnostics=self.diagnostics)  # fmt: skip


SWITCH_FLAGS: dict[str, Flag] = {name: Flag(SWITCH_HELP[name], metavar="on|off") for name in SWITCHES}


# -- files ----------------------------------------------------------------------------------------
def read_text(path: Path, what: str = "config file") -> str:
    """A user-named text file; a missing or unreadable one is one ConfigError line."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{what} {path} cannot be read ({e.__class__.__name__})") from None


def read_toml(path: Path, what: str = "config file") -> dict[str, Any]:
    """A TOML file as a table; every way it can fail is one ConfigError line."""
    path = Path(path)
    text = read_text(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{what} {path} is not valid TOML: {str(e).splitlines()[0]}") from None


def read_table(path: Path, what: str = "config file") -> dict[str, Any]:
    """A TOML file, or a YAML one (``.yaml``/``.yml``, the ``experiments`` extra), as a table.

    Raises:
        ConfigError: missing, unreadable, not valid TOML/YAML, or not a table at the top.
        MissingExtraError: a YAML file without PyYAML installed.
    """
    path = Path(path)
    if path.suffix.lower() not in (".yaml", ".yml"):
        return read_toml(path, what)
    text = read_text(path, what)
    try:
        import yaml
    except ImportError as e:
        raise MissingExtraError("experiments", f"the YAML {what} {path}") from e
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError(f"{what} {path} is not valid YAML: {str(e).splitlines()[0]}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{what} {path} must hold a table of keys, got {type(raw).__name__}")
    return raw
