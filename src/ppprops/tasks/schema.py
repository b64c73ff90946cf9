"""The task file's schema: every key, its type and its constraints, declared once as pydantic models.

``validate_table(raw, where)`` checks a task file's table (after ``extends``) and returns a
``TaskFile``; every problem is one ``TaskFileError`` line that names the file and the key
(``task file robot.toml: max_episode_steps must be a positive integer, got 0``). Each field's
``description`` is what a value of it must be, so the error lines are written from the schema
itself. ``ppprops.tasks.spec`` turns a ``TaskFile`` into the stored ``TaskSpec``; the
``[privacy]`` table validates directly into the facts model the declaration stores
(``tasks.facts.PrivacyFacts``).

Two kinds of task share the schema (docs/own-robot.md):

- with ``env``: ppprops makes the env (a Gymnasium id, ``module:EnvId`` or ``module:attr``) and
  reads the observation and action spaces from it; everything else is optional;
- without ``env``: a robot outside Python, driven through ask/tell. The file declares only what
  the policy sees and does: ``observation.values``, ``action_type``, ``actions`` and, for
  continuous actions, ``action_low`` / ``action_high``; feedback comes from the user's ``tell``,
  so components and diagnostics have names and meanings but no ``info`` key.
"""

from __future__ import annotations

import difflib
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from ..errors import ConfigError
from .facts import TABLE, Number, PrivacyFacts, Text
from .feedback import REDUCE, RESERVED

Bound = Annotated[float, Field(allow_inf_nan=True)]  # an action bound may be +-inf, never NaN (checked below)


class TaskFileError(ConfigError):
    """A task file (or the equivalent flags / Python arguments) declares something impossible."""


class _Table(BaseModel):
    model_config = TABLE


# -- feedback ------------------------------------------------------------------------------------
class ComponentEntry(_Table):
    """A reward component: ``name = "meaning"`` or ``name = { info = KEY, description = ... }``."""

    info: Text | None = Field(default=None, description="an info key")
    description: str = Field(default="", description="a string (the component's meaning)")
    reduce: Literal["sum"] = Field(default="sum", description="sum")


class DiagnosticEntry(_Table):
    """A diagnostic: ``name = "meaning"`` or ``name = { info = KEY, reduce = ..., description = ... }``."""

    info: Text | None = Field(default=None, description="an info key")
    description: str = Field(default="", description="a string (the diagnostic's meaning)")
    reduce: Literal["last", "mean", "sum", "min", "max"] | None = Field(default=None, description=", ".join(REDUCE))


def _entries(value: Any) -> Any:
    """``name = "meaning"`` is short for ``name = { description = "meaning" }``."""
    if isinstance(value, Mapping):
        return {k: {"description": v} if isinstance(v, str) else v for k, v in value.items()}
    return value


# -- observation ---------------------------------------------------------------------------------
class ObservationTable(_Table):
    """``[observation]``: which values of the env's observation the policy sees, and what each means."""

    keys: list[Text] | None = Field(default=None, description="a list of strings (the Dict entries kept, in order)")
    indices: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] | None = Field(default=None, description="a non-empty list of integers >= 0")
    select: list[Text] | None = Field(default=None, description="a list of strings (names of observation.values)")
    values: dict[str, str] = Field(default_factory=dict, description='a table of name = "meaning" (one string per value)')

    @model_validator(mode="after")
    def _consistent(self) -> ObservationTable:
        if self.indices is not None and len(set(self.indices)) != len(self.indices):
            raise ValueError(f"observation.indices names a value twice: {self.indices!r}")
        if self.select is not None and self.indices is not None:
            raise ValueError("give observation.indices or observation.select, not both")
        missing = [n for n in self.select or () if n not in self.values]
        if missing:
            raise ValueError(f"observation.select names {missing[0]!r}, which observation.values does not describe")
        if self.select is None and self.indices is not None and self.values and len(self.values) != len(self.indices) \
                and max(self.indices) >= len(self.values):  # fmt: skip
            raise ValueError(f"observation.values describes {len(self.values)} values; give one per kept value "
                             f"({len(self.indices)}) or one per value of the whole observation")  # fmt: skip
        return self


# -- the task file -------------------------------------------------------------------------------
class TaskFile(_Table):
    """A task file's table after ``extends`` (every key: docs/own-robot.md)."""

    format: str | None = Field(default=None, description="a string")
    name: Text = Field(description="a non-empty string")
    prompt_name: Text | None = Field(default=None, description="a non-empty string (the name the prompt may show)")
    env: Text | None = Field(default=None, description="a Gymnasium id, module:EnvId, or module:attr")
    imports: list[Text] = Field(default_factory=list, description="a list of strings (module names)")
    max_episode_steps: Annotated[int, Field(ge=1)] | None = Field(default=None, description="a positive integer")
    env_kwargs: dict[str, Any] = Field(default_factory=dict, description="a table (the env constructor's keyword arguments)")
    observation: ObservationTable = Field(default_factory=ObservationTable, description="a table")
    action_type: Literal["discrete", "continuous"] | None = Field(default=None, description="discrete or continuous")
    actions: list[Text] = Field(default_factory=list, description="a list of strings (one per policy output)")
    action_low: Bound | list[Bound] | None = Field(default=None, description="a number or a list of numbers, one per action")
    action_high: Bound | list[Bound] | None = Field(default=None, description="a number or a list of numbers, one per action")
    components: dict[str, ComponentEntry] = Field(
        default_factory=dict, description='a string or a table (name = "meaning" or name = { info = KEY, ... })')
    diagnostics: dict[str, DiagnosticEntry] = Field(
        default_factory=dict, description='a string or a table (name = "meaning" or name = { info = KEY, reduce = ..., ... })')
    summary: Text | None = Field(default=None, description="a non-empty string")
    reward_structure: Text | None = Field(default=None, description="a non-empty string")
    reward_hint: Text | None = Field(default=None, description="a non-empty string")
    hints: Text | None = Field(default=None, description="a non-empty string")
    optimal_return: Number | None = Field(default=None, description="a number")
    recorder: Text | None = Field(default=None, description="module:name of a recorder")
    setup: Text | None = Field(default=None, description="module:function of a setup check")
    privacy: PrivacyFacts = Field(default_factory=PrivacyFacts, description="a table")
    policy: dict[str, Any] | None = Field(default=None, description="a table (kind = \"linear\" or \"mlp\", hidden = [16], activation)")

    @field_validator("components", "diagnostics", mode="before")
    @classmethod
    def _to_entries(cls, value: Any) -> Any:
        return _entries(value)

    @model_validator(mode="after")
    def _consistent(self) -> TaskFile:
        if self.env is None:
            self._check_without_env()
        elif self.action_low is not None or self.action_high is not None:
            raise ValueError("action_low and action_high are read from the env's action space: give them only in a task "
                             "without env")  # fmt: skip
        if self.action_type == "discrete" and (self.action_low is not None or self.action_high is not None):
            raise ValueError("action_low and action_high bound continuous actions; a discrete action has none")
        if self.action_low is not None or self.action_high is not None:
            self.bounds()  # checks them
        for kind, table in (("components", self.components), ("diagnostics", self.diagnostics)):
            if any(not name.strip() for name in table):
                raise ValueError(f"{kind} has an empty name")
        self._check_facts()
        return self

    def _check_without_env(self) -> None:
        needs_env = [k for k in ("imports", "max_episode_steps", "env_kwargs", "recorder", "setup") if getattr(self, k)]
        needs_env += [f"observation.{k}" for k in ("keys", "indices", "select") if getattr(self.observation, k) is not None]
        if needs_env:
            raise ValueError(f"{needs_env[0]} needs an env, and this task has none (no env key): a task without env "
                             "declares only what the policy sees (observation.values) and does (action_type, actions)")  # fmt: skip
        missing = [k for k, v in (("observation.values", self.observation.values), ("action_type", self.action_type),
                                  ("actions", self.actions)) if not v]  # fmt: skip
        if missing:
            raise ValueError(f"no env is given, so this is a task for a robot outside Python, and it must declare "
                             f"{', '.join(missing)} (or give env: a Gymnasium id, module:EnvId, or module:attr)")  # fmt: skip
        if self.action_type == "continuous" and (self.action_low is None or self.action_high is None):
            raise ValueError("a task without env must give action_low and action_high for continuous actions (a number "
                             "for every action, or a list with one per action)")  # fmt: skip
        for kind, table in (("components", self.components), ("diagnostics", self.diagnostics)):
            for name, entry in table.items():
                if entry.info is not None or entry.reduce not in (None, "sum" if kind == "components" else "last"):
                    key = "info" if entry.info is not None else "reduce"
                    raise ValueError(f"{kind}.{name}.{key} reads an env's info, and this task has none: its feedback is "
                                     "what the robot's driver tells (name = \"meaning\")")  # fmt: skip

    def bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """The declared continuous action bounds, one (low, high) pair per action; None when not given."""
        if self.action_low is None or self.action_high is None:
            return None
        n = len(self.actions)
        out = []
        for key, v in (("action_low", self.action_low), ("action_high", self.action_high)):
            values = list(v) if isinstance(v, list) else [v] * n
            if len(values) != n or any(x != x for x in values):  # x != x: NaN
                raise ValueError(f"{key} must be a number or a list of {n} numbers (one per action), got {v!r}")
            out.append(tuple(float(x) for x in values))
        low, high = out
        bad = [j for j in range(n) if low[j] > high[j]]
        if bad:
            raise ValueError(f"action {bad[0]} has action_low {low[bad[0]]:g} > action_high {high[bad[0]]:g}")
        return low, high

    def _check_facts(self) -> None:
        p = self.privacy
        components = set(self.components)
        diagnostics = set(self.diagnostics) | set(RESERVED)
        named = [("privacy.survive_component", p.survive_component, components),
                 ("privacy.ctrl_component", p.ctrl_component, components),
                 ("privacy.residual_component", p.residual_component, components)]  # fmt: skip
        named += [("privacy.return_formula", k, diagnostics) for k in (p.return_formula or {})]
        named += [("privacy.return_determining", k, diagnostics) for k in p.return_determining or ()]
        named += [("privacy.caps", c.diagnostic, diagnostics) for c in p.caps or ()]
        named += [("privacy.resolution", k, components | {"return"}) for k in p.resolution or {}]
        if p.residual_component is False and self.components:
            raise ValueError("privacy.residual_component is false, but the task has components: name the one pp-hardened "
                             "leaves out (with every component shown, their sum gives the reward secrets away)")  # fmt: skip
        for key, value, known in named:
            if isinstance(value, str) and value not in known:
                what = "component" if known is components else "diagnostic" if known is diagnostics else "quantity"
                have = ", ".join(sorted(known)) or "none declared"
                raise ValueError(f"{key} names {what} {value!r}, which this task does not declare (it has: {have})")


# -- one-line errors -----------------------------------------------------------------------------
def _plain(value: Any) -> Any:
    """Tuples as lists and mappings as dicts, recursively (Python callers pass either; the schema is strict)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def validate_table(raw: Mapping[str, Any], where: str) -> TaskFile:
    """A task file's table (after ``extends``) checked against the schema.

    ``where`` starts every error (``task file robot.toml``). Raises TaskFileError: one line naming
    the key (an unknown key, with the closest known one; a wrong type; a value out of range; a
    combination the schema refuses).
    """
    table = _plain(raw)
    try:
        return TaskFile.model_validate(table)
    except ValidationError as e:
        raise TaskFileError(f"{where}: {describe_error(e.errors(include_url=False), table)}") from None


def describe_error(errors: Sequence[Mapping[str, Any]], table: Mapping[str, Any]) -> str:
    """The first of pydantic's errors on ``table`` (a ``TaskFile`` input) as the line a user reads, without the file.

    An unknown key comes first: a misspelt key also makes the key it meant missing.
    """
    err = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    kind, loc, ctx = err["type"], tuple(err["loc"]), err.get("ctx") or {}
    if kind == "value_error" and ctx.get("error") is not None:
        return str(ctx["error"])  # a check of several keys, worded where it is made
    if kind == "extra_forbidden":
        key = ".".join(map(str, [*_field_at(loc[:-1])[0], loc[-1]]))  # fmt: skip
        known = sorted(_fields_of(loc[:-1]))
        close = difflib.get_close_matches(str(loc[-1]), known, n=1)
        hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(known)}"
        return f"unknown key {key!r} ({hint})"
    shown, real, field, whole = _field_at(loc)
    key = ".".join(map(str, shown))
    if kind == "missing":
        return f"{key} is required"
    expect = "a table" if whole else (field.description if field is not None else None) or "a valid value"
    return f"{key} must be {expect}, got {_value_at(table, real)!r}"


def _walk(annotation: Any) -> list[Any]:
    """The model classes and container element types an annotation may hold (through Annotated, unions, lists, dicts)."""
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _walk(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [t for a in typing.get_args(annotation) for t in _walk(a)]
    return [annotation]


def _model_of(annotation: Any) -> tuple[type[BaseModel] | None, str]:
    """(model class the annotation validates into, what comes first in a loc: "" for a model itself, "dict" for
    a table of named models (a name), "list" for a list of them (a position))."""
    for t in _walk(annotation):
        origin = typing.get_origin(t)
        if isinstance(t, type) and issubclass(t, BaseModel):
            return t, ""
        if origin in (dict, list):
            inner = typing.get_args(t)[-1]
            for u in _walk(inner):
                if isinstance(u, type) and issubclass(u, BaseModel):
                    return u, "dict" if origin is dict else "list"
    return None, ""


def _field_at(loc: tuple[Any, ...]) -> tuple[list[Any], list[Any], Any, bool]:
    """(the user's key path in ``loc`` without list positions, the same with them, the schema field it ends
    at, whether it ends at a table of named entries itself rather than at one entry).

    Union branch tags (``constrained-str``) and whatever lies below a field that is not a table end the path.
    """
    model: type[BaseModel] | None = TaskFile
    shown: list[Any] = []
    real: list[Any] = []
    field = None
    skip_name = False
    container = ""
    for part in loc:
        if skip_name:  # a component's name, a list position
            real.append(part)
            if not isinstance(part, int):
                shown.append(part)
            skip_name = False
            continue
        if model is None or not isinstance(part, str) or part not in model.model_fields:
            break
        field = model.model_fields[part]
        shown.append(part)
        real.append(part)
        model, container = _model_of(field.annotation)
        skip_name = bool(container)
        if model is None:
            break
    return shown, real, field, skip_name and container == "dict"


def _fields_of(loc: tuple[Any, ...]) -> list[str]:
    """The keys the table at ``loc`` may hold."""
    model: type[BaseModel] | None = TaskFile
    skip_name = False
    for part in loc:
        if skip_name:
            skip_name = False
            continue
        if model is None or part not in model.model_fields:
            break
        model, container = _model_of(model.model_fields[part].annotation)
        skip_name = bool(container)
    return list(model.model_fields) if model is not None else []


def _value_at(table: Any, path: Sequence[Any]) -> Any:
    node = table
    for part in path:
        if isinstance(node, Mapping) and part in node:
            node = node[part]
        elif isinstance(node, list) and isinstance(part, int) and 0 <= part < len(node):
            node = node[part]
        else:
            return None
    return node


__all__ = ["REDUCE", "RESERVED", "ComponentEntry", "DiagnosticEntry", "ObservationTable", "TaskFile", "TaskFileError", "describe_error",
           "validate_table"]  # fmt: skip
