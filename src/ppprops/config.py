"""Run settings: one schema, validated by pydantic, stored with the run.

``RunConfig`` (with its ``LLMConfig`` and the method's ``Mechanisms``) is what a run stores and
resumes from; ``tasks.options.TaskOptions`` is how a user names the task, which becomes the
config's ``task`` and ``task_spec`` (the task's whole declaration). Every user-facing setting is a
field of one of them carrying a ``Flag``: its ``ppprops run`` flag, help text and error wording. ``ppprops.settings``
derives the command-line flags, the keys of config and experiment-spec files and the
one-line errors from these fields, so a setting is declared once, here.

Constructing any of these classes validates it (types, choices, bounds, and the checks that
involve several fields); a bad value is one ``ConfigError`` line naming the flag, e.g.
``--warmup must be >= 1 (the history starts from it), got 0``.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass

from .client.context import PromptSettings
from .client.hardening import EncodingSettings
from .errors import ConfigError, MissingExtraError
from .llm.settings import LLMConfig
from .methods import SWITCH_HELP, SWITCHES, Mechanisms, search_method_names
from .schema import SCHEMA, Box, Flag, Int, JsonObject, OnOff, one_line_errors
from .stopping import StopRules

if TYPE_CHECKING:
    from .tasks import Task

__all__ = ["LLMConfig", "OnOff", "PromptSettings", "RunConfig", "StopRules", "read_table", "read_text", "read_toml"]

# Sane upper bounds: past these a typo is far likelier than intent, and a run would not finish.
MAX_WARMUP = 10_000
MAX_ITERATIONS = 100_000
MAX_EPISODES = 10_000
MAX_PARSE_RETRIES = 10
MAX_PARALLEL = 256
ON_LLM_FAILURE = ("stop", "skip")
PROMPT_PARAMS = ("list", "indexed")  # see ppprops.wire.prompt.PARAMS_STYLES
PROMPT_LAYOUTS = ("static-first", "history-first")


@one_line_errors
@dataclass(frozen=True, config=SCHEMA)
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
        "LLM iterations, i.e. candidates (a round of --parallel P counts P); r2po: LLM calls, two per two-stage "
        "iteration; random, cmaes: samples")] = 50
    top_k: Annotated[Int, Field(ge=0), Flag("history entries in the prompt; 0 = all", hint="0 keeps every entry", group="prompt")] = 10
    episodes: Annotated[Int, Field(ge=1, le=MAX_EPISODES), Flag("episodes per candidate", default_text="1; 20 for r2po", group="evaluation")] = 1
    final_episodes: Annotated[Int, Field(ge=0, le=MAX_EPISODES), Flag("fresh episodes for the best policy", group="evaluation")] = 20
    # The selection stage (proposers.selection): the top candidates of the search run again on fresh
    # episodes, and the best pooled mean is handed over. None: 5 for a task with an env, 0 without one.
    select_top: Annotated[Int | None, Field(ge=0, le=MAX_EPISODES), Flag(
        "candidates of the search re-evaluated on fresh episodes before the best is chosen (0: none, the best "
        "search-time return is handed over)", default_text="5; 0 for a task without an env", group="evaluation")] = None
    select_episodes: Annotated[Int, Field(ge=1, le=MAX_EPISODES), Flag(
        "fresh episodes per re-evaluated candidate", group="evaluation")] = 10
    seed: Annotated[Int, Field(ge=0, lt=2**63), Flag(
        "run seed; the draws the provider sees are keyed by it and the run's fresh secrets, so it repeats a run "
        "only with the same secrets (a grid's master.key: ppprops experiment)", range_text="[0, 2^63)",
        default_text="drawn from the OS, printed and stored")] = 0
    box: Annotated[Box, Flag("feasible range of every parameter", metavar="LOW,HIGH", default_text="-6,6")] = (-6.0, 6.0)
    decimals: Annotated[Int, Field(ge=0, le=8), Flag("decimals of numbers in the prompt", range_text="[0, 8]", group="prompt")] = 2
    parse_retries: Annotated[Int, Field(ge=0, le=MAX_PARSE_RETRIES), Flag("corrections asked for before a fallback", group="prompt")] = 2
    llm: LLMConfig = Field(default_factory=LLMConfig)
    stop: StopRules = Field(default_factory=StopRules)  # when the search ends before its budget (ppprops.stopping)
    on_llm_failure: Annotated[Literal["stop", "skip"], Flag(
        "when the endpoint stays down past --retries: stop, resumable, or skip: record a fallback candidate and go on",
        group="llm")] = "stop"
    workers: Annotated[Int, Field(ge=1, le=256), Flag("processes running episodes in parallel", range_text="[1, 256]", group="evaluation")] = 1
    # Trials out at once (study.Study.ask): a round of P LLM requests from one shown history, P
    # samples of random search or CMA-ES, P trials held by workers; 1 keeps one trial at a time.
    parallel: Annotated[Int, Field(ge=1, le=MAX_PARALLEL), Flag(
        "trials out at once: the LLM proposes P per round from the same shown history (P concurrent requests), "
        "and P trials can be held by workers; --iterations still counts candidates", range_text=f"[1, {MAX_PARALLEL}]",
        group="evaluation")] = 1
    on_episode_error: Annotated[Literal["stop", "fail-trial"], Flag(
        "when an episode of the env raises: stop the run (resumable), or record the trial as failed with the error "
        "as its reason and go on (never shown to the LLM, never selected)", group="evaluation")] = "stop"
    components: tuple[str, ...] = ()  # runs stored before task_spec existed: a generic task's component info keys
    diagnostics: tuple[str, ...] = ()  # the same, for diagnostics
    prompt_params: Annotated[Literal["list", "indexed"], Flag(
        "history parameters as one list (compact) or as ProPS-style params[i]: value pairs", group="prompt", api_name="params")] = "list"
    # None: the prompt form's default (wire.forms.PromptForm.default_digits: 3 for chat, 2 for the document form)
    param_digits: Annotated[Int | None, Field(ge=0, le=8), Flag(
        "significant digits of each parameter, at most --decimals decimals; 0 = fixed decimals",
        range_text="[0, 8]", default_text="3 in the chat form's list, 2 in the document form", group="prompt", api_name="digits")] = None
    # The document form's exploration rule (wire.document.STALL_AFTER, EXPLORE_TEMPERATURE)
    explore: Annotated[OnOff, Flag("document form: after 3 LLM iterations without a new best shown return, sample one at "
                                   "temperature 2.0 (wire.document.EXPLORE_TEMPERATURE)", metavar="on|off", default_text="on",
                                   group="prompt")] = True
    prompt_layout: Annotated[Literal["static-first", "history-first"], Flag(
        "fixed sections before the history (a server's prefix cache reuses them) or history first", group="prompt",
        api_name="layout")] = "static-first"
    # chat: the paper's instruction prompt (/chat/completions); document: the history as a document for a
    # base model to continue (/completions, wire.document); auto: document for the embedded model, chat otherwise
    prompt_form: Annotated[Literal["auto", "chat", "document"], Flag(
        "chat: the paper's instruction prompt; document: the history as a document for a base model to continue "
        "(completions endpoint); auto: document for the embedded model, chat otherwise", group="prompt", api_name="form")] = "auto"
    # How encoded parameters are written (wire.numbers.NUMBER_FORMATS): grid, integers on a secret global grid
    # (client.codec); decimal, significant digits (the default). auto: grid when parameters are encoded, decimal otherwise.
    # Runs stored before formats existed are decimal (from_json).
    number_format: Annotated[Literal["auto", "grid", "decimal"], Flag(
        "how encoded parameters are written: grid (integers on a secret global grid, fewest tokens) or decimal "
        "(significant digits, the paper's); auto: grid when parameters are encoded, decimal when they are sent raw",
        group="prompt")] = "decimal"
    # The task's whole declaration (ppprops.tasks.spec.TaskSpec.model_dump(mode="json")): env recipe, observation
    # adapter, feedback keys, prose. Stored with every run, so any process rebuilds the task from it;
    # None in a config built from a task name (the run stores the declaration when it starts).
    task_spec: dict[str, Any] | None = None
    # Warm starts (ppprops.warm_start): the policies given with --init-policy, as given (paths or "python"), and their raw
    # parameters, read once when the run is made and stored with it: the warm-up's first trials.
    init_policy: Annotated[tuple[str, ...], Flag(
        "a policy to evaluate first, in a warm-up trial's place (repeatable): a ppprops policy file of this task, or JSON with W "
        "and b (u = s @ W + b) or with theta", metavar="PATH", repeatable=True, api_name="init_policies")] = ()
    init_thetas: tuple[tuple[float, ...], ...] = ()
    # The method's own options (ppprops.methods.Method.options checks them): e.g. CMA-ES's population size.
    method_options: Annotated[JsonObject, Flag(
        "the method's own options as a JSON object, e.g. '{\"popsize\": 8}' for cmaes (docs/baselines.md)",
        metavar="JSON")] = None

    @model_validator(mode="after")
    def _consistent(self) -> RunConfig:
        from .methods import get_method

        lo, hi = self.box
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"--box must be two finite numbers LOW < HIGH, got {lo}, {hi}")
        get_method(self.method).check_settings(self.mechanisms, prompt_form=self.prompt_form, options=self.method_options)
        if self.parallel > 1:
            budget, what = (self.iterations, f"--iterations {self.iterations}") if self.iterations else (self.warmup, f"--warmup {self.warmup}")
            if self.parallel > budget:
                raise ConfigError(f"--parallel {self.parallel} is larger than the budget ({what} candidates): "
                                  f"use at most --parallel {budget}")
            if not get_method(self.method).parallel:
                raise ConfigError(f"--method {self.method} asks one candidate at a time (each of its steps waits for the "
                                  f"last one's result): use --parallel 1")
        if len(self.init_thetas) > self.warmup:
            raise ConfigError(f"--init-policy: {len(self.init_thetas)} policies given, more than the warm-up holds (--warmup {self.warmup})")
        if self.number_format == "grid" and not self.mechanisms.encode_params:
            from .methods import resolve

            raw = "--encode-params off" if resolve(self.method).encode_params else f"--method {self.method}"
            raise ConfigError(f"--number-format grid needs encoded parameters; {raw} sends them raw (use decimal or auto)")
        return self

    @property
    def numbers(self) -> str:
        """The number format of this run's parameters (``auto`` resolved): grid when they are encoded, else decimal."""
        if self.number_format == "auto":
            return "grid" if self.mechanisms.encode_params else "decimal"
        return self.number_format

    def selection(self, has_env: bool = True) -> tuple[int, int]:
        """(candidates re-evaluated, episodes each) of the selection stage: ``select_top`` (None: 5
        for a task with an env, 0 without one) and ``select_episodes``."""
        top = self.select_top if self.select_top is not None else (5 if has_env else 0)
        return top, self.select_episodes

    @property
    def prompt(self) -> PromptSettings:
        """The settings the prompts depend on, in this run's form (``prompt_settings``)."""
        return self.prompt_settings(self.form)

    def prompt_settings(self, form: str) -> PromptSettings:
        """The settings the prompts of ``form`` (``chat`` or ``document``) depend on: what
        ``client.context.prompt_context`` and the proposers take instead of the whole config."""
        return PromptSettings(mechanisms=self.mechanisms, box=self.box, decimals=self.decimals, params_style=self.prompt_params,
                              param_digits=self.digits(form), layout=self.prompt_layout, top_k=self.top_k, form=form,
                              explore=self.explore is not False, number_format=self.numbers)

    @property
    def encoding(self) -> EncodingSettings:
        """The settings the secrets and the codec depend on (``client.hardening``)."""
        return EncodingSettings(mechanisms=self.mechanisms, box=self.box, episodes=self.episodes, grid=self.numbers == "grid")

    def digits(self, form: str | None = None) -> int:
        """Significant digits of a parameter in the prompt of ``form`` (default: this run's form)."""
        from .wire.forms import FORMS

        return self.param_digits if self.param_digits is not None else FORMS[form or self.form].default_digits

    @property
    def form(self) -> str:
        """The prompt form this run uses (``auto`` resolved): the document form for the embedded model
        (a base model) when the method takes it, the chat form otherwise."""
        if self.prompt_form == "auto":
            from .methods import get_method
            from .wire.forms import CHAT, DOCUMENT

            return DOCUMENT.name if self.llm.embedded and DOCUMENT.name in get_method(self.method).forms else CHAT.name
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
        if not self.method_options:
            del d["method_options"]  # as stored before methods had options
        if not self.stop.given:
            del d["stop"]  # as stored before the stop rules existed
        if self.llm.price is None:
            del d["llm"]["price"]  # as stored before prices
        else:
            d["llm"]["price"] = list(self.llm.price)
        if not self.init_thetas:
            del d["init_policy"], d["init_thetas"]  # as stored before warm starts existed
        else:
            d["init_thetas"] = [list(t) for t in self.init_thetas]
        for key, default in (("parallel", 1), ("on_episode_error", "stop")):
            if d[key] == default:
                del d[key]  # as stored before trials could run side by side or fail
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
        d["stop"] = StopRules(**d.get("stop", {}))
        for key in ("box", "components", "diagnostics", "init_policy"):
            if key in d:
                d[key] = tuple(d[key])
        if "init_thetas" in d:
            d["init_thetas"] = tuple(tuple(t) for t in d["init_thetas"])
        d.setdefault("prompt_form", "chat")  # runs stored before the document form existed chatted
        d.setdefault("number_format", "decimal")  # runs stored before the grid existed wrote decimals
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


SWITCH_FLAGS: dict[str, Flag] = {name: Flag(SWITCH_HELP[name], metavar="on|off") for name in SWITCHES}


# -- files ----------------------------------------------------------------------------------------
def read_text(path: Path, what: str = "config file") -> str:
    """A user-named text file; a missing or unreadable one is one ConfigError line."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        from .fileio import read_error

        raise ConfigError(f"{what} {path} cannot be read: {read_error(e)}") from None


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
