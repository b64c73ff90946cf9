"""Run settings as users give them: ``ppprops run`` flags, config files, experiment-spec tables.

Every setting is a field of the schema in ``ppprops.config`` (and ``tasks.options``) that carries a ``Flag`` (``TaskOptions``,
``RunConfig``, ``LLMConfig``) or a mechanism switch of ``ppprops.methods.Mechanisms``. ``SETTINGS``
lists them once, and everything here is derived from it:

- ``add_flags`` adds them to an argparse parser (names, types, choices, help with the default);
  their argparse default is "not given", so a parsed namespace holds only what the user typed;
- ``read_settings`` checks the values of a config-file or spec table (TOML/YAML types), keyed like
  the flags (``top-k`` or ``top_k``);
- ``build_config`` turns the given settings (a file's under the command line's, say) into the
  validated ``RunConfig``: the method's mechanisms with the switches given, its default episodes,
  the task's name and declaration.

Every error is one ``ConfigError`` line naming the flag or key.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import functools
import types
import typing
from collections.abc import Callable, Collection, Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BeforeValidator, TypeAdapter, ValidationError

from .config import SWITCH_FLAGS, LLMConfig, RunConfig
from .errors import ConfigError
from .methods import SWITCHES, Mechanisms, get_method
from .schema import Flag, OnOff, describe_error, flag_info
from .stopping import StopRules
from .tasks.options import TaskOptions

if typing.TYPE_CHECKING:
    from .tasks import Task

_BOUND_ERRORS = {"greater_than_equal", "greater_than", "less_than_equal", "less_than"}


@dataclasses.dataclass(frozen=True)
class Setting:
    """One user setting: a schema field and how it is given.

    Attributes:
        key: the canonical key, the flag's name with underscores (the argparse dest): ``top_k``,
            ``timeout``, ``component``.
        flag: the command-line flag, ``--top-k``.
        owner: the schema class holding the field (``TaskOptions``, ``RunConfig``, ``LLMConfig``,
            ``Mechanisms`` for a switch).
        field: the field's name in ``owner`` (``timeout_s`` for ``--timeout``).
        annotation: the field's type with its constraints (for checking one value).
        default: the field's default (None for a switch: the method's preset decides).
        info: help text and error wording.
        group: ``task``, ``run``, ``mechanisms``, ``llm`` or ``stop``.
    """

    key: str
    flag: str
    owner: type
    field: str
    annotation: Any
    default: Any
    info: Flag
    group: str

    @property
    def api_group(self) -> str | None:
        """Where ``ppprops.search`` / ``create_study`` take this setting: an option group (``llm``,
        ``privacy``, ``prompt``, ``evaluation``, ``task_options``), or None for a keyword of its own
        (``method``, ``warmup``, ``iterations``, ``seed``, ``box``, ``method_options``) and for
        ``env`` / ``task_file`` (the ``task`` argument)."""
        if self.owner is Mechanisms:
            return "privacy"
        if self.owner is LLMConfig:
            return "llm"
        if self.owner is StopRules:
            return "stop"
        if self.owner is TaskOptions:
            return None if self.key in ("env", "task_file", "policy", "activation") else "task_options"
        return self.info.group

    @property
    def api_name(self) -> str:
        """The key of this setting in its option group (``Flag.api_name``, else the setting's key)."""
        return self.info.api_name or self.key

    @property
    def names(self) -> tuple[str, ...]:
        """The keys a file may use: the flag's name with dashes and with underscores."""
        return tuple(dict.fromkeys((self.flag[2:], self.key)))

    def help_text(self, suffix: str = "") -> str:
        """The help line: the field's help, then its default (or ``suffix``, which says it instead)."""
        if suffix:
            return self.info.help + suffix
        shown = self.info.default_text
        if shown is None and self.default is not None and self.group != "mechanisms" and not self.info.repeatable:
            shown = "-6,6" if isinstance(self.default, tuple) else f"{self.default:g}" if isinstance(self.default, float) else str(self.default)
        return self.info.help + (f" (default {shown})" if shown else "") + suffix

    @functools.cached_property
    def _adapter(self) -> TypeAdapter[Any]:
        return TypeAdapter(self.annotation)

    def check(self, value: Any, where: str, key: str) -> Any:
        """A file's ``key = value`` as the value of this setting, checked for type and choices.

        Bounds and checks of several fields are left to ``build_config``, which names the flag.
        Raises ConfigError ``<where>: <key> ...``.
        """
        if self.info.choices is not None and value not in self.info.choices():
            raise ConfigError(f"{where}: {key} must be one of {', '.join(self.info.choices())}, got {value!r}")
        if self.info.repeatable and not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise ConfigError(f"{where}: {key} must be a list of strings, got {value!r}")
        try:
            return self._adapter.validate_python(value)
        except ValidationError as e:
            errors = e.errors()
            if all(err["type"] in _BOUND_ERRORS for err in errors):
                return value  # the right type; its range is checked with the whole config
            err = errors[0]
            if err["type"] == "value_error":
                if "box" in self.key:
                    raise ConfigError(f"{where}: {key} = {value!r} is not a valid value ({err['ctx']['error']})") from None
                raise ConfigError(f"{where}: {key}: {err['ctx']['error']}") from None
            raise ConfigError(f"{where}: {describe_error(err, key, self.info)}") from None

    def parse_flag(self) -> Callable[[str], Any]:
        """The argparse ``type`` of the flag: the field's own parser when it has one, else its base type."""
        parser = next((m.func for m in _metadata(self.annotation) if isinstance(m, BeforeValidator)), None)
        if parser is None:
            base = _base_type(self.annotation)
            return base if base in (int, float, Path) else str

        def parse(text: str) -> Any:
            try:
                return parser(text)  # type: ignore[call-arg]
            except ValueError as e:
                raise argparse.ArgumentTypeError(str(e)) from None

        parse.__name__ = self.key
        return parse

    def choices(self) -> Collection[str] | None:
        """The allowed values of a choice setting (a ``Literal`` field: a list; ``Flag.choices``: its
        collection as it is, which may be lazy, like the ``--method`` choices of ``methods.MethodChoices``)."""
        if self.info.choices is not None:
            return self.info.choices()
        literal = _literal(self.annotation)
        return list(literal) if literal else None


def _metadata(annotation: Any) -> list[Any]:
    if typing.get_origin(annotation) is typing.Annotated:
        return list(annotation.__metadata__) + _metadata(typing.get_args(annotation)[0])
    return []


def _strip(annotation: Any) -> Any:
    """The type under Annotated and Optional."""
    while True:
        if typing.get_origin(annotation) is typing.Annotated:
            annotation = typing.get_args(annotation)[0]
            continue
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if typing.get_origin(annotation) in (typing.Union, types.UnionType) and len(args) == 1:
            annotation = args[0]
            continue
        return annotation


def _literal(annotation: Any) -> tuple[str, ...]:
    tp = _strip(annotation)
    return tuple(typing.get_args(tp)) if typing.get_origin(tp) is Literal else ()


def _base_type(annotation: Any) -> Any:
    tp = _strip(annotation)
    return typing.get_origin(tp) or tp


def _fields_of(owner: type, group: str) -> list[Setting]:
    out = []
    for name, info in owner.__pydantic_fields__.items():  # type: ignore[attr-defined]
        flag = flag_info(owner, name)
        if flag is None:
            continue  # stored, not set by users (task, task_spec, mechanisms, llm, legacy keys)
        key = (flag.name or name).replace("-", "_")
        annotation = typing.Annotated[info.annotation, *info.metadata] if info.metadata else info.annotation
        default = info.default if info.default is not dataclasses.MISSING else None
        default = None if repr(default) == "PydanticUndefined" else default
        out.append(Setting(key, "--" + key.replace("_", "-"), owner, name, annotation, default, flag, group))
    return out


def _all_settings() -> tuple[Setting, ...]:
    switches = [Setting(name, "--" + name.replace("_", "-"), Mechanisms, name, OnOff, None, SWITCH_FLAGS[name], "mechanisms")
                for name in SWITCHES]  # fmt: skip
    return (*_fields_of(TaskOptions, "task"), *_fields_of(RunConfig, "run"), *switches, *_fields_of(LLMConfig, "llm"),
            *_fields_of(StopRules, "stop"))


SETTINGS: tuple[Setting, ...] = _all_settings()
BY_KEY: dict[str, Setting] = {s.key: s for s in SETTINGS}
_BY_NAME: dict[str, Setting] = {name: s for s in SETTINGS for name in s.names}

API_GROUPS = ("llm", "privacy", "prompt", "evaluation", "stop", "task_options")


def api_groups() -> dict[str, dict[str, Setting]]:
    """The option groups of ``ppprops.search`` / ``create_study``, derived from ``SETTINGS``:
    group -> {the key a user writes in it: the setting}."""
    out: dict[str, dict[str, Setting]] = {g: {} for g in API_GROUPS}
    for s in SETTINGS:
        if s.api_group is not None:
            out[s.api_group][s.api_name] = s
    return out


GROUP_TITLES = {
    "mechanisms": "mechanisms (override the preset one by one)",
    "llm": "LLM endpoint (default: the embedded Gemma 3 270M, offline)",
    "stop": "stopping early (the selection stage and the final evaluation still run)",
}


# -- command line ---------------------------------------------------------------------------------
def add_flags(parser: argparse.ArgumentParser | argparse._ArgumentGroup, *, exclude: Iterable[str] = (), only: Iterable[str] | None = None,
              groups: Mapping[str, str] | None = GROUP_TITLES, help_suffix: str = "") -> None:  # fmt: skip
    """Add the settings' flags to ``parser`` (keys in ``exclude`` left out, or only those in ``only``).

    Each flag's argparse default is ``SUPPRESS``: the parsed namespace holds only the flags given,
    and ``build_config`` (or a file's values under them) supplies the rest. ``groups`` maps a
    setting group to the title of an argument group (None: every flag at the top).
    """
    exclude, keep = set(exclude), None if only is None else set(only)
    made: dict[str, Any] = {}
    for s in SETTINGS:
        if s.key in exclude or (keep is not None and s.key not in keep):
            continue
        target: Any = parser
        if groups and s.group in groups:
            target = made.setdefault(s.group, parser.add_argument_group(groups[s.group]))
        kw: dict[str, Any] = {"dest": s.key, "default": argparse.SUPPRESS, "help": s.help_text(help_suffix)}
        if s.info.metavar:
            kw["metavar"] = s.info.metavar
        choices = s.choices()
        if s.info.repeatable:
            kw["action"] = "append"
        elif choices is not None:
            kw["choices"] = choices
            if not isinstance(choices, list):  # lazy (plugins): argparse would list it when the flag is added
                kw.setdefault("metavar", s.key.upper())
                kw["help"] += " (one of: %(choices)s)"
        else:
            kw["type"] = s.parse_flag()
        target.add_argument(s.flag, **kw)


def given(namespace: argparse.Namespace) -> dict[str, Any]:
    """The settings a parsed namespace holds (the flags the user gave), by key."""
    return {k: v for k, v in vars(namespace).items() if k in BY_KEY}


# -- files ----------------------------------------------------------------------------------------
def setting_for(key: str) -> Setting | None:
    """The setting a file key names (``top-k``, ``top_k``), or None."""
    return _BY_NAME.get(key)


def read_settings(table: Mapping[str, Any], where: str, *, unknown: str = "unknown key", reserved: Mapping[str, str] | None = None,
                  exclude: Iterable[str] = ()) -> dict[str, Any]:  # fmt: skip
    """Check a table of settings (a config file, a spec's ``[run]``) and return it by key.

    ``where`` starts every error (``config file run.toml``); ``unknown`` names an unknown key in it
    (``unknown key 'warmpu' (did you mean warmup?)``); ``reserved`` maps keys a caller sets itself
    to the error to give for them; ``exclude`` are keys this caller does not take.

    Raises:
        ConfigError: an unknown or reserved key, or a value of the wrong type.
    """
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where} must be a table of run settings, got {table!r}")
    exclude = set(exclude)
    names = sorted({s.flag[2:] for s in SETTINGS if s.key not in exclude})
    out: dict[str, Any] = {}
    for key, value in table.items():
        if reserved and key in reserved:
            raise ConfigError(f"{where}: {key} {reserved[key]}")
        s = setting_for(key)
        if s is None or s.key in exclude:
            close = difflib.get_close_matches(str(key).replace("_", "-"), names, n=1)
            hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(names)}"
            raise ConfigError(f"{where}: {unknown} {key!r} ({hint})")
        out[s.key] = s.check(value, where, key)
    return out


# -- the config -----------------------------------------------------------------------------------
def task_options(values: Mapping[str, Any]) -> TaskOptions:
    """The ``TaskOptions`` among the given settings."""
    return TaskOptions(**{s.field: values[s.key] for s in SETTINGS if s.owner is TaskOptions and s.key in values})


# run settings that shape the prompt or the LLM's answers: nothing to do for a method that sends no prompt
PROMPT_SETTINGS = ("top_k", "decimals", "parse_retries", "on_llm_failure", "prompt_params", "param_digits", "explore",
                   "prompt_layout", "prompt_form", "number_format")


def refuse_prompt_settings(method_name: str, keys: Iterable[str]) -> None:
    """Refuse LLM and prompt settings given for a method that sends no prompt (random search, CMA-ES).

    ``keys``: the settings the user gave explicitly (the command line's). A grid's shared settings
    are not checked: there the same table serves its prompted and black-box runs alike.

    Raises:
        ConfigError: one line naming the flags, as for a mechanism switch (``Method.mechanisms``).
    """
    method = get_method(method_name)
    if method.uses_llm or not method.is_search:
        return
    bad = [BY_KEY[k].flag for k in keys if k in BY_KEY and (BY_KEY[k].group == "llm" or k in PROMPT_SETTINGS)]
    if bad:
        one = len(bad) == 1
        raise ConfigError(f"{', '.join(bad)} {'does' if one else 'do'} not apply to --method {method.name}: "
                          f"it sends no prompt (drop {'it' if one else 'them'})")


def check_fits_context(config: RunConfig, task: Task) -> None:
    """Refuse, before any request, an MLP whose one answer cannot fit the embedded model's context,
    and an MLP for R2PO (its critic reads a linear policy's rollout).

    A prompted method's answer holds D numbers (``wire.forms.answer_budget``: 24 + 8 D tokens, more
    with the document form's labels) and its prompt at least one history entry of as many; together
    they must fit ``--context-size``. Only an MLP is checked (the paper's linear policies fit); a
    remote endpoint's context is not known before it answers (its context-full answers stop the run
    with their own line).

    Raises:
        ConfigError: one line with D, the tokens needed and the limit.
    """
    from .wire.forms import FORMS

    if not task.policy.is_linear and get_method(config.method).phase == "r2po_phase":
        raise ConfigError(f"--method {config.method} searches the linear policy only (its critic reads a linear rollout): "
                          f"--policy {task.policy.label().split()[0]} needs --method pp, random or cmaes")
    if task.policy.is_linear or not get_method(config.method).uses_llm or not config.llm.embedded:
        return
    answer = FORMS[config.form].answer_tokens(task.D)
    needed = 2 * answer
    limit = config.llm.context_size
    if needed > limit:
        raise ConfigError(f"--policy {task.policy.label().split()[0]} is too large for the endpoint's context: D = {task.D} parameters, "
                          f"so one answer needs about {answer} tokens and the prompt's history at least as many ({needed} in all), "
                          f"more than the embedded model's context of {limit} tokens (--context-size): use fewer hidden units")  # fmt: skip


def build_config(values: Mapping[str, Any], *, task: Task | None = None) -> RunConfig:
    """The RunConfig of the given settings (by key; those not given take the schema's defaults).

    The method's registry entry gives the mechanisms (its preset, with the switches given) and the
    default episodes. The task comes from the task settings (``--env`` / ``--task-file`` and their
    options), made only after every other setting passed, or is ``task`` when the caller made it.

    Raises:
        ConfigError: one line naming the flag: a value out of range, no task, an unknown task or
            method, a mechanism the method refuses.
    """
    unknown = sorted(set(values) - set(BY_KEY))
    if unknown:
        raise ConfigError(f"unknown setting(s): {', '.join(unknown)}")
    options = task_options(values) if task is None else None
    if options is not None and options.env is None and options.task_file is None:
        raise ConfigError("--env or --task-file is required (on the command line, or in the --config file)")
    method = get_method(values.get("method", "pp"))
    mechanisms = method.mechanisms(**{s.key: values[s.key] for s in SETTINGS if s.owner is Mechanisms and s.key in values})
    run = {s.field: values[s.key] for s in SETTINGS if s.owner is RunConfig and s.key in values}
    run.setdefault("episodes", method.default_episodes)
    run["method"] = method.name
    llm = LLMConfig(**{s.field: values[s.key] for s in SETTINGS if s.owner is LLMConfig and s.key in values})
    stop = StopRules(**{s.field: values[s.key] for s in SETTINGS if s.owner is StopRules and s.key in values})
    if llm.model and llm.base_url is None:  # the embedded model would answer, and the run would record a model that never did
        raise ConfigError(f"--model {llm.model} names a model at --base-url, and no --base-url was given (the embedded model "
                          "answers without one): give --base-url too, or drop --model")
    name = task.name if task is not None else str(options.env or options.task_file) if options is not None else ""
    config = RunConfig(task=name, mechanisms=mechanisms, llm=llm, stop=stop, **run)  # every number checked before an env is made
    from .tasks import is_builtin, load_task

    if task is None:
        assert options is not None
        task = load_task(options=options)
    check_fits_context(config, task)
    if config.init_policy:
        from .warm_start import init_thetas

        config = dataclasses.replace(config, init_thetas=init_thetas(config.init_policy, task, box=config.box, warmup=config.warmup))

    return dataclasses.replace(config, task=task.name, task_spec=None if is_builtin(task) or task.spec is None else task.spec.model_dump(mode="json"))
