"""The building blocks of the settings schema: how a field appears to a user, and one-line errors.

Every user-facing setting is a field of a pydantic dataclass carrying a ``Flag`` (its ``ppprops
run`` flag, help text and error wording). The schema classes live with the layer they configure
(``ppprops.llm.settings.LLMConfig`` for the endpoint, ``ppprops.config.RunConfig`` for a run);
``ppprops.settings`` derives the command-line flags and file keys from them. Constructing a class
decorated with ``one_line_errors`` raises one ``ConfigError`` line naming the flag instead of
pydantic's multi-line ``ValidationError``.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass as plain_dataclass
from typing import Annotated, Any, TypeVar

from pydantic import BeforeValidator, ConfigDict, Strict, ValidationError

from .errors import ConfigError


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
        group: the option group of ``ppprops.search`` / ``create_study`` the setting is given in
            (``prompt``, ``evaluation``, ``llm``), for a run setting that is not a keyword of its own;
            ``settings.Setting.api_group`` says where every setting goes.
        api_name: its key in that group when not the setting's key (``form`` for ``--prompt-form``).
    """

    help: str
    name: str | None = None
    metavar: str | None = None
    range_text: str | None = None
    hint: str = ""
    default_text: str | None = None
    repeatable: bool = False
    choices: Callable[[], Collection[str]] | None = None
    group: str | None = None
    api_name: str | None = None


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

SCHEMA = ConfigDict(extra="forbid", arbitrary_types_allowed=True)
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
