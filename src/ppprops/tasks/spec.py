"""Tasks as data: the task file (TOML), its ``TaskSpec``, and resolving a spec against its env.

A ``TaskSpec`` is a task's whole declaration: how to make the env (``EnvRecipe``), which parts of
the observation the policy sees, what the observed values and the actions mean, the reward
components and diagnostics with the info keys they come from, and the prompt's prose. It is stored
with every run (``RunConfig.task_spec``) and in every policy file, so any process rebuilds the task
from it without the code that first declared it.

A task file::

    name = "Reacher2D"
    env = "my_robot:Reacher2D"     # a Gymnasium id, module:EnvId, or module:attr (an Env class or a
                                   # function returning an env); module may be a file next to this one
    max_episode_steps = 200        # required when the env has no time limit of its own
    imports = ["my_robot_envs"]    # modules imported first (packages that register ids)
    optimal_return = 0.0           # optional; stated only by presets that disclose it
    summary = "..."                # what the robot is and what it should do
    reward_structure = "..."       # the reward with its numbers (only disclosing presets show it)
    reward_hint = "..."            # qualitative, no numbers (every preset shows it)
    hints = "..."
    actions = ["...", "..."]       # one line per policy output
    [env_kwargs]                   # passed to the env's constructor
    [observation]
    keys = ["observation", "desired_goal"]   # a Dict observation: the entries kept, in this order
    indices = [0, 1, 2, 10, 11, 12]          # values kept of the (flattened) observation
    [observation.values]                     # name = meaning; for the kept values, or for all of them
    [components]                             # name = meaning (info key = name), or a table:
    reward_ctrl = { info = "ctrl_cost", description = "..." }
    [diagnostics]
    distance = { info = "dist", reduce = "last", description = "..." }

``extends = "base.toml"`` starts from another file (tables merged, other values replaced). A
Discrete observation becomes a one-hot vector, so the linear policy is a table of action scores.
The paper's tasks are files of this kind (``ppprops/tasks/paper``); they also name a ``recorder``
(code that derives feedback from each step) and a ``setup`` (a check for a simulator extra).
"""

from __future__ import annotations

import difflib
import json
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np

from ..errors import ConfigError, UnknownTaskError
from .base import Selection, Task, TaskText
from .envs import (
    EnvRecipe,
    Prepare,
    TaskImportError,
    check_json_kwargs,
    entry_point_of,
    has_time_limit,
    import_module,
    import_root,
    load_attr,
)
from .feedback import MISSING, REDUCE, RESERVED, FeedbackKeyError, InfoFeedback, InfoKey, check_value, lookup, missing_key

FORMAT = "ppprops.task/1"
PROBE_STEPS = 10_000  # longest probe episode of an env with no time limit
_TEXT = "ppprops.tasks.descriptions"
FILE_KEYS = ("name", "env", "extends", "imports", "max_episode_steps", "env_kwargs", "observation", "actions", "action_type",
             "components", "diagnostics", "summary", "reward_structure", "reward_hint", "hints", "optimal_return",
             "recorder", "setup", "format")  # fmt: skip
OBSERVATION_KEYS = ("keys", "indices", "select", "values")


class TaskFileError(ConfigError):
    """A task file (or the equivalent flags / Python arguments) declares something impossible."""


@dataclass(frozen=True)
class Declared:
    """A reward component or diagnostic: its name, meaning, and the info key it is read from.

    ``info`` is None for feedback a task's ``recorder`` computes itself. A name ending in ``.*``
    asks for every entry of a dict-valued info key; resolving the task expands it.
    """

    name: str
    description: str = ""
    info: str | None = None
    reduce: str = "last"

    def to_json(self) -> dict[str, Any]:
        """The stored form."""
        return {"name": self.name, "description": self.description, "info": self.info, "reduce": self.reduce}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Declared:
        """The inverse of ``to_json``."""
        return cls(name=str(d["name"]), description=str(d.get("description", "")), info=d.get("info"),
                   reduce=str(d.get("reduce", "last")))  # fmt: skip


@dataclass(frozen=True)
class TaskSpec:
    """A task's whole declaration (see the module docstring). ``complete`` specs know every count.

    ``observation`` holds ``keys`` / ``one_hot`` / ``indices`` and the ``names`` and ``descriptions``
    of the kept values (empty until resolved against the env when the file gave none). ``actions``
    describes each policy output; ``action_type`` is ``"discrete"`` (argmax) or ``"continuous"``
    (clipped to the action bounds).
    """

    name: str
    env: EnvRecipe
    keys: tuple[str, ...] | None = None
    indices: tuple[int, ...] | None = None
    one_hot: tuple[int, int] | None = None
    names: tuple[str, ...] = ()
    descriptions: tuple[str, ...] = ()
    action_type: str | None = None
    actions: tuple[str, ...] = ()
    components: tuple[Declared, ...] = ()
    diagnostics: tuple[Declared, ...] = ()
    recorder: str | None = None
    summary: str = ""
    reward_structure: str = ""
    reward_hint: str = ""
    hints: str = ""
    optimal_return: float | None = None
    complete: bool = False  # every count known and checked against the env (or a paper task)

    def to_json(self) -> dict[str, Any]:
        """The declaration as JSON values (what a run and a policy file store)."""
        return {
            "format": FORMAT,
            "name": self.name,
            "env": self.env.to_json(),
            "observation": {"keys": _list(self.keys), "indices": _list(self.indices),
                            "one_hot": None if self.one_hot is None else {"n": self.one_hot[0], "start": self.one_hot[1]},
                            "names": list(self.names), "descriptions": list(self.descriptions)},  # fmt: skip
            "action_type": self.action_type,
            "actions": list(self.actions),
            "components": [c.to_json() for c in self.components],
            "diagnostics": [d.to_json() for d in self.diagnostics],
            "recorder": self.recorder,
            "summary": self.summary,
            "reward_structure": self.reward_structure,
            "reward_hint": self.reward_hint,
            "hints": self.hints,
            "optimal_return": self.optimal_return,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> TaskSpec:
        """A stored declaration (``to_json``); complete by construction."""
        if d.get("format") != FORMAT:
            raise TaskFileError(f"stored task is not a {FORMAT} declaration")
        obs = d["observation"]
        oh = obs.get("one_hot")
        return cls(
            name=str(d["name"]),
            env=EnvRecipe.from_json(d["env"]),
            keys=_tuple(obs.get("keys")),
            indices=None if obs.get("indices") is None else tuple(int(i) for i in obs["indices"]),
            one_hot=None if oh is None else (int(oh["n"]), int(oh["start"])),
            names=tuple(obs["names"]),
            descriptions=tuple(obs["descriptions"]),
            action_type=d["action_type"],
            actions=tuple(d["actions"]),
            components=tuple(Declared.from_json(c) for c in d.get("components", ())),
            diagnostics=tuple(Declared.from_json(c) for c in d.get("diagnostics", ())),
            recorder=d.get("recorder"),
            summary=d.get("summary", ""),
            reward_structure=d.get("reward_structure", ""),
            reward_hint=d.get("reward_hint", ""),
            hints=d.get("hints", ""),
            optimal_return=d.get("optimal_return"),
            complete=True,
        )

    def with_options(
        self,
        *,
        env_kwargs: Mapping[str, Any] | None = None,
        max_episode_steps: int | None = None,
        gym_packages: Sequence[str] = (),
        obs_keys: Sequence[str] | None = None,
        components: Sequence[str] = (),
        diagnostics: Sequence[str] = (),
    ) -> TaskSpec:
        """This declaration with the quick options of ``ppprops run`` applied (they win); not yet resolved."""
        env = self.env
        if env_kwargs:
            env = replace(env, kwargs={**env.kwargs, **check_json_kwargs(env_kwargs, self.name)})
        if max_episode_steps is not None:
            if max_episode_steps < 1:
                raise TaskFileError(f"--max-episode-steps must be >= 1, got {max_episode_steps}")
            env = replace(env, max_episode_steps=int(max_episode_steps))
        if gym_packages:
            env = replace(env, imports=tuple(dict.fromkeys((*env.imports, *gym_packages))))
        spec = replace(self, env=env)
        if obs_keys is not None:
            spec = replace(spec, keys=tuple(obs_keys), indices=None, names=(), descriptions=(), one_hot=None)
        if components or diagnostics:
            comps = self.components + tuple(Declared(k, info=k, reduce="sum") for k in components)
            diags = self.diagnostics + tuple(Declared(k, info=k) for k in diagnostics)
            spec = replace(spec, components=comps, diagnostics=diags)
        return replace(spec, complete=False)


def _list(v: Sequence[Any] | None) -> list[Any] | None:
    return None if v is None else list(v)


def _tuple(v: Sequence[Any] | None) -> tuple[Any, ...] | None:
    return None if v is None else tuple(v)


# -- reading task files ------------------------------------------------------------------------
def _read_file(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A task file's table with ``extends`` applied and its relative paths made absolute."""
    path = Path(path)
    if path in seen:
        raise TaskFileError(f"task file {path}: extends itself (through {' -> '.join(map(str, seen))})")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TaskFileError(f"task file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise TaskFileError(f"task file {path} cannot be read ({e.__class__.__name__})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise TaskFileError(f"task file {path} is not valid TOML: {str(e).splitlines()[0]}") from None
    unknown = [k for k in raw if k not in FILE_KEYS]
    if unknown:
        close = difflib.get_close_matches(unknown[0], FILE_KEYS, n=1)
        hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(FILE_KEYS)}"
        raise TaskFileError(f"task file {path}: unknown key {unknown[0]!r} ({hint})")
    env = raw.get("env")
    if isinstance(env, str) and ":" in env:
        module, _, attr = env.rpartition(":")
        if module.endswith(".py"):  # a file next to the task file: import it by name from its folder
            file = (path.parent / module).resolve()
            raw["env"] = f"{file.stem}:{attr}"
            raw.setdefault("paths", [])
            raw["paths"] = [str(file.parent)]
    if "extends" in raw:
        base_name = raw.pop("extends")
        if not isinstance(base_name, str):
            raise TaskFileError(f"task file {path}: extends must be a file name, got {base_name!r}")
        base = _read_file((path.parent / base_name).resolve(), (*seen, path))
        raw = _merge(base, raw)
    return raw


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def read_task_file(path: str | Path, *, builtin: bool = False) -> TaskSpec:
    """Parse a task file into a TaskSpec (not yet resolved against its env; see ``resolve``)."""
    path = Path(path)
    raw = _read_file(path if builtin else path.resolve())
    paths = raw.pop("paths", [])
    if not builtin:
        paths = [*paths, str(path.resolve().parent)]  # modules next to the task file import
    return spec_from_table(raw, where=f"task file {path}", paths=tuple(dict.fromkeys(paths)), builtin=builtin)


def spec_from_table(raw: Mapping[str, Any], *, where: str, paths: tuple[str, ...] = (), builtin: bool = False) -> TaskSpec:
    """A TaskSpec from a task file's table (after ``extends``); ``builtin`` marks the paper's own files."""
    name = _str(raw, "name", where, required=True)
    env_text = raw.get("env")
    factory = None
    if callable(env_text) and not builtin:  # a dict from Python may hold the env factory itself
        factory = spec_for_env(env_text, name=name).env
        env_text = factory.id
    if not isinstance(env_text, str) or not env_text:
        raise TaskFileError(f"{where}: env is required (a Gymnasium id, module:EnvId, or module:attr)")
    imports = _strings(raw, "imports", where)
    kwargs = raw.get("env_kwargs", {})
    if not isinstance(kwargs, Mapping):
        raise TaskFileError(f"{where}: env_kwargs must be a table, got {kwargs!r}")
    steps = raw.get("max_episode_steps")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        raise TaskFileError(f"{where}: max_episode_steps must be a positive integer, got {steps!r}")
    recipe = EnvRecipe(id=env_text, kwargs=check_json_kwargs(kwargs, where), max_episode_steps=steps, imports=imports, paths=paths,
                       setup=_str(raw, "setup", where))  # fmt: skip
    if factory is not None:
        recipe = replace(recipe, entry_point=factory.entry_point, paths=tuple(dict.fromkeys(paths + factory.paths)))
    elif not builtin:
        recipe = _entry_point_recipe(recipe, where)
    obs = raw.get("observation", {})
    if not isinstance(obs, Mapping):
        raise TaskFileError(f"{where}: observation must be a table, got {obs!r}")
    bad = [k for k in obs if k not in OBSERVATION_KEYS]
    if bad:
        raise TaskFileError(f"{where}: unknown key observation.{bad[0]} (known: {', '.join(OBSERVATION_KEYS)})")
    keys = _strings(obs, "keys", where, none=True)
    indices = obs.get("indices")
    if indices is not None:
        if not (isinstance(indices, list) and indices and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in indices)):
            raise TaskFileError(f"{where}: observation.indices must be a non-empty list of integers >= 0, got {indices!r}")
        if len(set(indices)) != len(indices):
            raise TaskFileError(f"{where}: observation.indices names a value twice: {indices!r}")
    select = _strings(obs, "select", where, none=True)
    if select is not None and indices is not None:
        raise TaskFileError(f"{where}: give observation.indices or observation.select, not both")
    values = obs.get("values", {})
    if not isinstance(values, Mapping) or not all(isinstance(v, str) for v in values.values()):
        raise TaskFileError(f"{where}: observation.values must be a table of name = \"meaning\"")
    names, descriptions = tuple(values), tuple(v.strip() for v in values.values())
    if select is not None:
        missing = [n for n in select if n not in values]
        if missing:
            raise TaskFileError(f"{where}: observation.select names {missing[0]!r}, which observation.values does not describe")
        indices = [names.index(n) for n in select]
        names, descriptions = tuple(select), tuple(values[n].strip() for n in select)
    elif indices is not None and names and len(names) != len(indices):
        if max(indices) >= len(names):
            raise TaskFileError(f"{where}: observation.values describes {len(names)} values; give one per kept value "
                                f"({len(indices)}) or one per value of the whole observation")  # fmt: skip
        names, descriptions = tuple(names[i] for i in indices), tuple(descriptions[i] for i in indices)
    action_type = raw.get("action_type")
    if action_type not in (None, "discrete", "continuous"):
        raise TaskFileError(f"{where}: action_type must be discrete or continuous, got {action_type!r}")
    actions = _strings(raw, "actions", where)
    optimal = raw.get("optimal_return")
    if optimal is not None and (isinstance(optimal, bool) or not isinstance(optimal, (int, float)) or not np.isfinite(optimal)):
        raise TaskFileError(f"{where}: optimal_return must be a number, got {optimal!r}")
    recorder = _str(raw, "recorder", where)
    components = _declared(raw.get("components", {}), "components", where, recorder is not None, default_reduce="sum")
    diagnostics = _declared(raw.get("diagnostics", {}), "diagnostics", where, recorder is not None, default_reduce="last")
    spec = TaskSpec(
        name=name,
        env=recipe,
        keys=keys,
        indices=None if indices is None else tuple(indices),
        names=names,
        descriptions=descriptions,
        action_type=action_type,
        actions=actions,
        components=components,
        diagnostics=diagnostics,
        recorder=recorder,
        summary=_str(raw, "summary", where) or "",
        reward_structure=_str(raw, "reward_structure", where) or "",
        reward_hint=_str(raw, "reward_hint", where) or "",
        hints=_str(raw, "hints", where) or "",
        optimal_return=None if optimal is None else float(optimal),
        complete=builtin,
    )
    if builtin:
        _check_complete(spec, where)
    return spec


@overload
def _str(raw: Mapping[str, Any], key: str, where: str, *, required: Literal[True]) -> str: ...
@overload
def _str(raw: Mapping[str, Any], key: str, where: str, *, required: bool = False) -> str | None: ...
def _str(raw: Mapping[str, Any], key: str, where: str, *, required: bool = False) -> str | None:
    v = raw.get(key)
    if v is None and not required:
        return None
    if not isinstance(v, str) or not v.strip():
        raise TaskFileError(f"{where}: {key} must be a non-empty string, got {v!r}")
    return v.strip()


def _strings(raw: Mapping[str, Any], key: str, where: str, *, none: bool = False) -> Any:
    v = raw.get(key)
    if v is None:
        return None if none else ()
    if not (isinstance(v, list) and all(isinstance(x, str) and x for x in v)):
        raise TaskFileError(f"{where}: {key} must be a list of strings, got {v!r}")
    return tuple(x.strip() for x in v)


def _declared(table: Any, kind: str, where: str, by_recorder: bool, *, default_reduce: str) -> tuple[Declared, ...]:
    if not isinstance(table, Mapping):
        raise TaskFileError(f"{where}: {kind} must be a table of name = \"meaning\" or name = {{ info = KEY, ... }}")
    out = []
    for name, v in table.items():
        if isinstance(v, str):
            v = {"description": v}
        if not isinstance(v, Mapping):
            raise TaskFileError(f"{where}: {kind}.{name} must be a string or a table, got {v!r}")
        bad = [k for k in v if k not in ("info", "description", "reduce")]
        if bad:
            raise TaskFileError(f"{where}: unknown key {kind}.{name}.{bad[0]} (known: info, description, reduce)")
        reduce = v.get("reduce", default_reduce)
        if reduce not in REDUCE or (kind == "components" and reduce != "sum"):
            allowed = "sum" if kind == "components" else ", ".join(REDUCE)
            raise TaskFileError(f"{where}: {kind}.{name}.reduce must be {allowed}, got {reduce!r}")
        info = v.get("info", None if by_recorder or name in RESERVED else name)
        if info is not None and (not isinstance(info, str) or not info):
            raise TaskFileError(f"{where}: {kind}.{name}.info must be an info key, got {info!r}")
        out.append(Declared(name=str(name), description=str(v.get("description", "")).strip(), info=info, reduce=reduce))
    return tuple(out)


def _entry_point_recipe(recipe: EnvRecipe, where: str) -> EnvRecipe:
    """``module:attr`` names an env class or factory unless ``attr`` is an id the module registers."""
    module, sep, attr = recipe.id.rpartition(":")
    if not sep:
        return recipe
    import gymnasium as gym

    from .envs import add_paths

    add_paths(recipe.paths)
    mod = import_module(module, where)
    root = import_root(module)
    if root is not None:
        recipe = replace(recipe, paths=tuple(dict.fromkeys((*recipe.paths, root))))
    if attr in gym.registry:
        return recipe  # the Gymnasium form module:EnvId
    if not callable(getattr(mod, attr.split(".")[0], None)):
        raise UnknownTaskError(f"{where}: module {module!r} has no env {attr!r} (neither an id it registers nor a class or "
                               "function returning an env)")  # fmt: skip
    return replace(recipe, entry_point=recipe.id)


def _check_complete(spec: TaskSpec, where: str) -> None:
    if not spec.names or len(spec.names) != len(spec.descriptions):
        raise TaskFileError(f"{where}: a paper task must describe every observed value")
    if spec.indices is not None and len(spec.indices) != len(spec.names):
        raise TaskFileError(f"{where}: {len(spec.names)} observed values for {len(spec.indices)} indices")
    if spec.action_type is None or not spec.actions:
        raise TaskFileError(f"{where}: a paper task must give action_type and actions")


# -- from Python objects and flags -------------------------------------------------------------
def spec_for_env(env: str | Callable[..., Any], *, name: str | None = None) -> TaskSpec:
    """A bare declaration for an env given by id / ``module:attr`` string or a factory callable."""
    if callable(env) and not isinstance(env, str):
        label = str(name or getattr(env, "__name__", "env"))
        found = entry_point_of(env)
        if found is None:  # a lambda or local function: reachable in this process through a registered id
            return TaskSpec(name=label, env=EnvRecipe(id=_register_local(env, label)))
        ref, paths = found
        return TaskSpec(name=label, env=EnvRecipe(id=ref, entry_point=ref, paths=paths))
    if not isinstance(env, str) or not env:
        raise TaskFileError(f"a task is a name, a Gymnasium id, module:attr, a task file, an env factory or a TaskSpec; got {env!r}")
    return TaskSpec(name=name or env, env=_entry_point_recipe(EnvRecipe(id=env), f"env {env!r}"))


def _register_local(factory: Callable[..., Any], label: str) -> str:
    """A Gymnasium id for a factory with no importable name (``ppprops-local/<label>-vN``)."""
    import re

    import gymnasium as gym

    stem = re.sub(r"[^A-Za-z0-9_]", "_", label) or "env"
    for version in range(1000):
        env_id = f"ppprops-local/{stem}-v{version}"
        reg = gym.registry.get(env_id)
        if reg is None:
            gym.register(id=env_id, entry_point=factory)
            return env_id
        if reg.entry_point is factory:
            return env_id
    raise TaskFileError(f"too many local env factories named {label!r}")


# -- resolving against the env -----------------------------------------------------------------
@cache
def _generic_text() -> dict[str, Any]:
    return tomllib.loads(resources.files(_TEXT).joinpath("generic.toml").read_text(encoding="utf-8"))


def _fmt(v: float) -> str:
    return f"{v:g}"


def _bounds(low: float, high: float) -> str:
    return _generic_text()["bounds"].format(low=_fmt(low), high=_fmt(high)) if np.isfinite(low) and np.isfinite(high) else ""


def _observation_layout(spec: TaskSpec, space: Any) -> tuple[tuple[int, int] | None, list[str], list[str]]:
    """One-hot of a Discrete observation, and a default (name, description) for every flattened value."""
    from gymnasium import spaces

    text = _generic_text()
    where = f"task {spec.name}"
    if isinstance(space, spaces.Dict):
        if spec.keys is None:
            raise TaskFileError(f"{spec.env.id} has a Dict observation ({', '.join(space.spaces)}); choose the entries the "
                                "policy sees with --obs-keys K1,K2 (or observation.keys in a task file)")  # fmt: skip
        names, descs = [], []
        for key in spec.keys:
            if key not in space.spaces:
                close = difflib.get_close_matches(key, list(space.spaces), n=1)
                hint = f"; did you mean {close[0]}?" if close else ""
                raise TaskFileError(f"{where}: the Dict observation of {spec.env.id} has no entry {key!r} "
                                    f"(it has {', '.join(space.spaces)}){hint}")  # fmt: skip
            sub = space.spaces[key]
            if not isinstance(sub, (spaces.Box, spaces.MultiBinary)):
                raise TaskFileError(f"{where}: observation entry {key!r} is a {type(sub).__name__}; entries must be Box spaces")
            lows = np.broadcast_to(np.asarray(getattr(sub, "low", 0.0), dtype=float), sub.shape).reshape(-1)
            highs = np.broadcast_to(np.asarray(getattr(sub, "high", 1.0), dtype=float), sub.shape).reshape(-1)
            for i in range(int(np.prod(sub.shape))):
                names.append(f"{key}_{i}")
                descs.append(text["observation_key"].format(index=i, key=key, bounds=_bounds(lows[i], highs[i])))
        return None, names, descs
    if spec.keys is not None:
        raise TaskFileError(f"{where}: observation keys {', '.join(spec.keys)} given, but {spec.env.id} observes a "
                            f"{type(space).__name__}, not a Dict")  # fmt: skip
    if isinstance(space, spaces.Discrete):
        n, start = int(space.n), int(space.start)
        return (n, start), [f"state_{start + i}" for i in range(n)], [text["observation_one_hot"].format(index=start + i) for i in range(n)]
    if isinstance(space, (spaces.Box, spaces.MultiBinary)):
        size = int(np.prod(space.shape))
        lows = np.broadcast_to(np.asarray(getattr(space, "low", 0.0), dtype=float), space.shape).reshape(-1)
        highs = np.broadcast_to(np.asarray(getattr(space, "high", 1.0), dtype=float), space.shape).reshape(-1)
        return None, [f"obs_{i}" for i in range(size)], [text["observation"].format(index=i, bounds=_bounds(lows[i], highs[i]))
                                                          for i in range(size)]  # fmt: skip
    raise TaskFileError(f"{spec.env.id} has a {type(space).__name__} observation; supported are Box, Discrete (one-hot) "
                        "and Dict of Box (choose entries with --obs-keys)")  # fmt: skip


def _action_layout(spec: TaskSpec, space: Any) -> tuple[str, list[str]]:
    from gymnasium import spaces

    text = _generic_text()
    if isinstance(space, spaces.Discrete):
        if int(space.start) != 0:
            raise TaskFileError(f"{spec.env.id}: Discrete actions starting at {space.start} are not supported")
        return "discrete", [text["action_discrete"].format(index=j) for j in range(int(space.n))]
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        lo, hi = np.asarray(space.low, dtype=float), np.asarray(space.high, dtype=float)
        return "continuous", [text["action_continuous"].format(index=j, bounds=_bounds(lo[j], hi[j])) for j in range(space.shape[0])]
    raise TaskFileError(f"{spec.env.id}: only 1-D Box or Discrete action spaces are supported, got {space}")


def resolve(spec: TaskSpec) -> TaskSpec:
    """Check a declaration against its env and complete it; one probe episode checks the feedback keys.

    Makes the env once: the observation and action spaces fill in the counts, one-hot size and any
    description the declaration left out, and must agree with what it gave. Then one episode with
    the zero policy (theta = 0): each declared component must be in the env's info from the first
    step and each diagnostic at some step of the episode, every one a scalar (``KEY.*`` is expanded
    into the entries of a dict-valued key here); an env with no time limit must end that episode
    within ``PROBE_STEPS`` steps. Every failure is one ConfigError line; nothing is run or stored.
    """
    if spec.complete:
        return spec
    recipe = spec.env.pinned()
    spec = replace(spec, env=recipe)
    env = recipe.make()
    try:
        return _resolve_with(spec, env)
    finally:
        env.close()


def _resolve_with(spec: TaskSpec, env: Any) -> TaskSpec:
    one_hot, all_names, all_descs = _observation_layout(spec, env.observation_space)
    size = len(all_names)
    where = f"task {spec.name}"
    indices = spec.indices
    if indices is not None:
        out = [i for i in indices if i >= size]
        if out:
            raise TaskFileError(f"{where}: observation index {out[0]} is out of range: the observation has {size} values (0-{size - 1})")
    kept = list(range(size)) if indices is None else list(indices)
    names, descs = spec.names, spec.descriptions
    if not names:
        names, descs = tuple(all_names[i] for i in kept), tuple(all_descs[i] for i in kept)
    elif len(names) == size and len(kept) != size:
        names, descs = tuple(names[i] for i in kept), tuple(descs[i] for i in kept)
    elif len(names) != len(kept):
        raise TaskFileError(f"{where}: observation.values describes {len(names)} values, but the policy sees {len(kept)} "
                            f"(of {size} in the observation)")  # fmt: skip
    action_type, action_descs = _action_layout(spec, env.action_space)
    if spec.action_type is not None and spec.action_type != action_type:
        raise TaskFileError(f"{where}: action_type is {spec.action_type}, but {spec.env.id} has {action_type} actions")
    actions = spec.actions or tuple(action_descs)
    if len(actions) != len(action_descs):
        raise TaskFileError(f"{where}: actions describes {len(actions)} outputs, but {spec.env.id} has {len(action_descs)}")
    spec = replace(spec, one_hot=one_hot, names=tuple(names), descriptions=tuple(descs), action_type=action_type, actions=tuple(actions))
    spec = _probe(spec, env)
    text = _generic_text()
    spec = replace(
        spec,
        summary=spec.summary or text["summary"].format(env_id=spec.env.id, n_s=len(spec.names), n_a=len(spec.actions)).strip(),
        reward_structure=spec.reward_structure or text["reward_structure"].strip(),
        reward_hint=spec.reward_hint or text["reward_hint"].strip(),
        hints=spec.hints or text.get("hints", "").strip(),
        components=tuple(replace(c, description=c.description or text["component"].format(key=c.info)) for c in spec.components),
        diagnostics=tuple(replace(d, description=d.description or _diag_text(d)) for d in spec.diagnostics if d.info is not None or d.description),
        complete=True,
    )
    _check_names(spec)
    return spec


def _diag_text(d: Declared) -> str:
    text = _generic_text()
    if d.reduce == "last":
        return text["diagnostic"].format(key=d.info)
    return text["diagnostic_reduced"].format(key=d.info, reduce=d.reduce)


def _check_names(spec: TaskSpec) -> None:
    names = [c.name for c in spec.components] + [d.name for d in spec.diagnostics]
    reserved = {d.name for d in (*spec.components, *spec.diagnostics) if d.name in RESERVED and d.info is not None}
    twice = sorted({n for n in names if names.count(n) > 1} | (reserved if spec.recorder is None else set()))
    if twice:
        raise TaskFileError(f"task {spec.name}: info key(s) declared twice or reserved: {', '.join(twice)}")
    if len(set(spec.names)) != len(spec.names):
        raise TaskFileError(f"task {spec.name}: two observed values share a name")


def _probe(spec: TaskSpec, env: Any) -> TaskSpec:
    """One zero-policy episode: expand ``KEY.*``, check every declared info key (see ``resolve``)."""
    from ..policy import LinearPolicy

    _check_names(spec)
    # a recorder reads the info itself: nothing declared to check, but the episode must still end
    declared = spec.recorder is None
    adapter = Selection(names=spec.names, indices=spec.indices, keys=spec.keys, one_hot=spec.one_hot)
    n_s, n_a = len(spec.names), len(spec.actions)
    space = env.action_space
    policy = LinearPolicy.from_flat(np.zeros((n_s + 1) * n_a), n_s, n_a, discrete=spec.action_type == "discrete",
                                    low=getattr(space, "low", None), high=getattr(space, "high", None))  # fmt: skip
    limited = has_time_limit(env)
    obs, info = env.reset(seed=0)
    s = adapter(obs)
    if s.shape != (n_s,):
        raise TaskFileError(f"task {spec.name}: the observation adapter gives {s.shape[0]} values, not {n_s}")
    components = list(spec.components) if declared else []
    computed = [d for d in spec.diagnostics if d.info is None or not declared]  # episode_length: ppprops counts it
    diagnostics = [d for d in spec.diagnostics if d.info is not None and declared]
    seen: set[str] = set()
    step = 0
    ended = False
    while step < PROBE_STEPS:
        obs, _, terminated, truncated, info = env.step(policy.act(adapter(obs)))
        step += 1
        if step == 1:
            components = _expand(spec.name, "component", components, info)
            diagnostics = _expand(spec.name, "diagnostic", diagnostics, info)
            for c in components:
                assert c.info is not None
                if check_value(spec.name, "component", InfoKey(c.name, c.info), info, where="at the first step") is None:
                    raise missing_key(spec.name, "component", InfoKey(c.name, c.info), info, where="at the first step")
        for d in diagnostics:
            assert d.info is not None
            if check_value(spec.name, "diagnostic", InfoKey(d.name, d.info), info, where=f"at step {step}") is not None:
                seen.add(d.name)
        if terminated or truncated:
            ended = True
            break
        if limited and len(seen) == len(diagnostics):
            break  # everything checked, and the time limit ends every episode
    if not ended and not limited and step >= PROBE_STEPS:
        raise TaskFileError(f"task {spec.name}: an episode of {spec.env.id} did not end within {PROBE_STEPS} steps and the env "
                            "has no time limit: give one with --max-episode-steps N (max_episode_steps in a task file)")  # fmt: skip
    unseen = [d for d in diagnostics if d.name not in seen]
    if unseen:
        d = unseen[0]
        assert d.info is not None
        raise missing_key(spec.name, "diagnostic", InfoKey(d.name, d.info), info, where="at any step of an episode")
    if not declared:
        return spec
    return replace(spec, components=tuple(components), diagnostics=(*computed, *diagnostics))


def _expand(task: str, kind: str, declared: list[Declared], info: Mapping[str, Any]) -> list[Declared]:
    out: list[Declared] = []
    for d in declared:
        assert d.info is not None
        if not d.info.endswith(".*"):
            out.append(d)
            continue
        parent = d.info[:-2]
        value = lookup(info, parent)
        if value is MISSING:
            raise missing_key(task, kind, InfoKey(d.name, parent), info, where="at the first step")
        if not isinstance(value, Mapping):
            raise FeedbackKeyError(f"{task}: {kind} {d.info!r} asks for the entries of {parent!r}, but that is a "
                                   f"{type(value).__name__} in the env's info, not a dict")  # fmt: skip
        stem = d.name[:-2] if d.name.endswith(".*") else d.name
        reduce = d.reduce
        out.extend(Declared(name=f"{stem}.{k}", info=f"{parent}.{k}", reduce=reduce) for k in value)
    return out


# -- building the Task -------------------------------------------------------------------------
def build_task(spec: TaskSpec) -> Task:
    """The Task the loop runs, from a complete declaration."""
    if not spec.complete:
        spec = resolve(spec)
    factory: Any
    if spec.recorder is not None:
        factory = load_attr(spec.recorder, f"task {spec.name}")
    else:
        factory = InfoFeedback(
            task=spec.name,
            components=tuple(InfoKey(c.name, c.info or c.name, "sum") for c in spec.components),
            diagnostics=tuple(InfoKey(d.name, d.info, d.reduce) for d in spec.diagnostics if d.info is not None),
        )
    diag_names = tuple(dict.fromkeys(("episode_length", *(d.name for d in spec.diagnostics))))
    diag_text = {"episode_length": _generic_text()["diagnostics"]["episode_length"]}
    diag_text.update({d.name: d.description for d in spec.diagnostics if d.description})
    text = TaskText(
        summary=spec.summary,
        observations=spec.descriptions,
        actions=spec.actions,
        reward_structure=spec.reward_structure,
        reward_hint=spec.reward_hint,
        hints=spec.hints,
        components={c.name: c.description for c in spec.components},
        diagnostics=diag_text,
    )
    assert spec.action_type in ("discrete", "continuous")
    return Task(
        name=spec.name,
        env_id=spec.env.id,
        n_s=len(spec.names),
        n_a=len(spec.actions),
        action_type=spec.action_type,  # type: ignore[arg-type]
        observation=Selection(names=spec.names, indices=spec.indices, keys=spec.keys, one_hot=spec.one_hot),
        feedback=factory,
        text=text,
        components=tuple(c.name for c in spec.components),
        diagnostics=diag_names,
        env_kwargs=dict(spec.env.kwargs),
        optimal_return=spec.optimal_return,
        setup=Prepare(spec.env),
        spec=spec,
    )


@cache
def _task_from_json_text(text: str) -> Task:
    return build_task(TaskSpec.from_json(json.loads(text)))


def task_from_json(d: Mapping[str, Any]) -> Task:
    """The task of a stored declaration (one Task object per distinct declaration in a process)."""
    try:
        return _task_from_json_text(json.dumps(d, sort_keys=True))
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        raise TaskFileError(f"stored task declaration is damaged ({type(e).__name__}: {e})") from None


__all__ = ["Declared", "TaskFileError", "TaskImportError", "TaskSpec", "build_task", "read_task_file", "resolve", "spec_for_env",
           "spec_from_table", "task_from_json"]  # fmt: skip
