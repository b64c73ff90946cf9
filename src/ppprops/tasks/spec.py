"""Tasks as data: the task file (TOML), its ``TaskSpec``, and resolving a spec against its env.

A ``TaskSpec`` is a task's whole declaration: how to make the env (``EnvRecipe``; none for a robot
outside Python), which parts of the observation the policy sees, what the observed values and the
actions mean, the reward components and diagnostics with the info keys they come from, the
prompt's prose and display name, and the task's privacy facts. It is stored with every run
(``RunConfig.task_spec``) and in every policy file, so any process rebuilds the task from it
without the code that first declared it. It is the one model of a declaration, a pydantic model
serialised by pydantic (``model_dump(mode="json")`` / ``model_validate``, format ``ppprops.task/1``).
A task file is read by its own input schema (``tasks.schema.TaskFile``: the file's syntax, such as
``name = "meaning"`` shorthands and the ``[observation.values]`` table, and the one-line errors that
name the file's keys), which ``spec_from_table`` turns into the one ``TaskSpec``; its ``[privacy]``
table validates directly into the facts the declaration stores (``tasks.facts.PrivacyFacts``).

A task file::

    name = "Reacher2D"
    prompt_name = "a planar arm"   # optional: the name a prompt may show the provider
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
    [privacy]                                # what an attacker may know (tasks.facts); absent = unknown
    public_env = false

Without ``env`` the file describes a robot outside Python, driven with ask/tell: it declares
``observation.values``, ``action_type``, ``actions`` and (continuous) ``action_low`` /
``action_high``, and nothing that needs an env (``tasks.schema``). ``extends = "base.toml"`` starts
from another file (tables merged, other values replaced). A Discrete observation becomes a one-hot
vector, so the linear policy is a table of action scores. The paper's tasks are files of this kind
(``ppprops/tasks/paper``); they also name a ``recorder`` (code that derives feedback from each step)
and a ``setup`` (a check for a simulator extra).

Loading a task makes its env once to read the observation and action spaces, and never resets or
steps it: the feedback keys are checked by the episodes of the run itself (``feedback.InfoFeedback``)
or, when asked, by one zero-policy episode (``ppprops.tasks.check.check_task``, ``ppprops task check``).
"""

from __future__ import annotations

import difflib
import json
import tomllib
from collections.abc import Callable, Mapping
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..errors import ConfigError, UnknownTaskError
from ..policy import LINEAR, PolicySpec, parse_policy
from .base import NoEnv, Selection, Task, TaskText
from .envs import EnvRecipe, Prepare, check_json_kwargs, entry_point_of, import_module, import_root, load_attr
from .facts import PrivacyFacts
from .feedback import InfoFeedback, InfoKey
from .schema import RESERVED, TaskFile, TaskFileError, validate_table

if TYPE_CHECKING:
    from .options import TaskOptions

FORMAT: Final = "ppprops.task/1"
_TEXT = "ppprops.tasks.descriptions"
LOCAL_PREFIX = "ppprops-local/"  # ids of env factories with no importable name (this process only)

# The declaration's models: lenient types (Python callers pass lists or tuples), frozen, and their
# validators built on first use, not when ppprops.tasks is imported.
_SPEC = ConfigDict(frozen=True, defer_build=True)


class Declared(BaseModel):
    """A reward component or diagnostic: its name, meaning, and the info key it is read from.

    ``info`` is None for feedback a task's ``recorder`` computes itself, and for every component
    and diagnostic of a task without env (its driver tells them). A name ending in ``.*`` asks for
    every entry of a dict-valued info key; only ``check_task``'s episode expands it.
    """

    model_config = _SPEC

    name: str
    description: str = ""
    info: str | None = None
    reduce: str = "last"

    @property
    def wildcard(self) -> bool:
        """True for ``KEY.*``: every entry of a dict-valued info key, named only after a step of the env."""
        return self.info is not None and self.info.endswith(".*")


class OneHot(BaseModel):
    """A Discrete observation as a one-hot vector: ``n`` values, the space's first state ``start``."""

    model_config = _SPEC

    n: int
    start: int


class ObservationSpec(BaseModel):
    """Which values of the env's observation the policy sees, and what each means.

    A Dict observation keeps ``keys`` (each flattened, concatenated in this order); a Discrete one
    becomes ``one_hot``; ``indices`` keep some values of the flattened result. ``names`` and
    ``descriptions`` describe the kept values (empty until resolved against the env when the file
    gave none).
    """

    model_config = _SPEC

    keys: tuple[str, ...] | None = None
    indices: tuple[int, ...] | None = None
    one_hot: OneHot | None = None
    names: tuple[str, ...] = ()
    descriptions: tuple[str, ...] = ()

    def selection(self) -> Selection:
        """The observation adapter of these values (``base.Selection``)."""
        one_hot = None if self.one_hot is None else (self.one_hot.n, self.one_hot.start)
        return Selection(names=self.names, indices=self.indices, keys=self.keys, one_hot=one_hot)


def _unset(value: Any) -> bool:
    return value is None


def _no_facts(value: PrivacyFacts | None) -> bool:
    return value is None or value.is_empty()


class TaskSpec(BaseModel):
    """A task's whole declaration (see the module docstring). ``complete`` specs know every count.

    Stored as ``model_dump(mode="json")`` (format ``ppprops.task/1``: keys added after its first
    version, ``action_low`` / ``action_high`` / ``prompt_name`` / ``privacy``, are written only when
    set, so a declaration that sets none of them is stored exactly as before) and read back with
    ``model_validate``, also a declaration an earlier ppprops stored: a stored declaration (it
    names its ``format``) is complete, and one without ``privacy`` predates the privacy facts
    (``privacy`` None: every fact unknown; ``ppprops.tasks.privacy_facts`` completes the paper's
    tasks).

    ``env`` is None for a task without env (a robot outside Python, driven with ask/tell); its
    continuous actions are bounded by ``action_low`` / ``action_high`` (one value per action). For a
    task with an env those are None: the env's action space bounds the actions. ``actions``
    describes each policy output; ``action_type`` is ``"discrete"`` (argmax) or ``"continuous"``
    (clipped to the action bounds). ``prompt_name`` is the name a prompt may show the provider
    (None: not set). ``privacy`` holds the declared privacy facts (``tasks.facts``). ``policy`` is
    the policy family searched (``ppprops.policy.PolicySpec``; None: the linear policy).
    """

    model_config = _SPEC

    format: Literal["ppprops.task/1"] = FORMAT
    name: str
    env: EnvRecipe | None
    observation: ObservationSpec = Field(default_factory=ObservationSpec)
    action_type: Literal["discrete", "continuous"] | None = None
    actions: tuple[str, ...] = ()
    components: tuple[Declared, ...] = ()
    diagnostics: tuple[Declared, ...] = ()
    recorder: str | None = None
    summary: str = ""
    reward_structure: str = ""
    reward_hint: str = ""
    hints: str = ""
    optimal_return: float | None = None
    action_low: tuple[float, ...] | None = Field(default=None, exclude_if=_unset)
    action_high: tuple[float, ...] | None = Field(default=None, exclude_if=_unset)
    prompt_name: str | None = Field(default=None, exclude_if=_unset)
    privacy: PrivacyFacts | None = Field(default_factory=PrivacyFacts, exclude_if=_no_facts)
    # the policy family (None: the paper's linear policy; stored only when set, so a linear declaration is stored as before)
    policy: PolicySpec | None = Field(default=None, exclude_if=_unset)
    # every count known: checked against the env's spaces, or declared (paper task, no env); not stored
    complete: bool = Field(default=False, exclude=True)

    @model_validator(mode="before")
    @classmethod
    def _stored(cls, data: Any) -> Any:
        """A stored declaration (one that names its format) is complete; without ``privacy`` it predates the facts."""
        if isinstance(data, Mapping) and "format" in data:
            return {"privacy": None, **data, "complete": True}
        return data

    @property
    def has_env(self) -> bool:
        """False for a task without env (a robot outside Python)."""
        return self.env is not None

    def public_env(self) -> bool:
        """Whether an attacker can build and simulate the env (privacy fact ``public_env``).

        The declared value when there is one. Otherwise True for an env every installation has
        under its plain id (a Gymnasium id, a paper task, an id of an installed package such as
        highway-env), and False for a user's env: ``module:attr`` or ``module:EnvId``, an env found
        through ``imports`` or a folder of the user's, a factory registered in this process, and a
        task without env.
        """
        if self.privacy is not None and self.privacy.public_env is not None:
            return self.privacy.public_env
        env = self.env
        if env is None:
            return False
        if ":" in env.id or env.id.startswith(LOCAL_PREFIX) or env.imports or env.paths:
            return False
        return env.entry_point is None or not env.entry_point.startswith(tuple(f"{m}." for m in ("__main__", "__mp_main__")))

    def with_options(self, options: TaskOptions) -> TaskSpec:
        """This declaration with the quick options of ``ppprops run`` applied (they win); not yet resolved.

        ``options`` is a ``tasks.options.TaskOptions``; its ``env`` and ``task_file`` (which name the task)
        are not read here. Raises TaskFileError for a task without env (every option but the
        feedback names concerns an env; a task without env declares its feedback in its file).
        """
        env = self.env
        if env is None:
            raise TaskFileError(f"task {self.name} has no env (a robot outside Python): --env-kwargs, --max-episode-steps, "
                                "--gym-packages, --obs-keys, --component and --diagnostic apply to an env; declare the "
                                "feedback in the task file")  # fmt: skip
        if options.env_kwargs:
            env = env.model_copy(update={"kwargs": {**env.kwargs, **check_json_kwargs(options.env_kwargs, self.name)}})
        if options.max_episode_steps is not None:
            env = env.model_copy(update={"max_episode_steps": options.max_episode_steps})
        if options.gym_packages:
            env = env.model_copy(update={"imports": tuple(dict.fromkeys((*env.imports, *options.gym_packages)))})
        update: dict[str, Any] = {"env": env, "complete": False}
        if options.obs_keys is not None:
            update["observation"] = ObservationSpec(keys=tuple(options.obs_keys))
        if options.components or options.diagnostics:
            update["components"] = self.components + tuple(Declared(name=k, info=k, reduce="sum") for k in options.components)
            update["diagnostics"] = self.diagnostics + tuple(Declared(name=k, info=k) for k in options.diagnostics)
        return self.model_copy(update=update)


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
        from ..fileio import read_error

        raise TaskFileError(f"task file {path} cannot be read: {read_error(e)}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise TaskFileError(f"task file {path} is not valid TOML: {str(e).splitlines()[0]}") from None
    env = raw.get("env")
    if isinstance(env, str) and ":" in env:
        module, _, attr = env.rpartition(":")
        if module.endswith(".py"):  # a file next to the task file: import it by name from its folder
            file = (path.parent / module).resolve()
            raw["env"] = f"{file.stem}:{attr}"
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
    """Parse a task file into a TaskSpec (not yet resolved against its env; see ``resolve``).

    Raises TaskFileError: one line naming the file and the key (``tasks.schema``).
    """
    path = Path(path)
    raw = _read_file(path if builtin else path.resolve())
    paths = raw.pop("paths", [])
    if not builtin:
        paths = [*paths, str(path.resolve().parent)]  # modules next to the task file import
    return spec_from_table(raw, where=f"task file {path}", paths=tuple(dict.fromkeys(paths)), builtin=builtin)


def spec_from_table(raw: Mapping[str, Any], *, where: str, paths: tuple[str, ...] = (), builtin: bool = False) -> TaskSpec:
    """A TaskSpec from a task file's table (after ``extends``); ``builtin`` marks the paper's own files.

    A table from Python may hold the env factory itself under ``env``. Raises TaskFileError: one
    line starting with ``where`` and naming the key (the schema: ``tasks.schema.TaskFile``).
    """
    raw = dict(raw)
    factory = None
    if callable(raw.get("env")) and not builtin:  # a dict from Python may hold the env factory itself
        factory = spec_for_env(raw["env"], name=str(raw.get("name") or "env")).env
        assert factory is not None
        raw["env"] = factory.id
    if "extends" in raw:
        raise TaskFileError(f"{where}: extends names a file next to a task file; a table given from Python cannot extend one")
    f = validate_table(raw, where)
    recipe = None
    if f.env is not None:
        recipe = EnvRecipe(id=f.env, kwargs=check_json_kwargs(f.env_kwargs, where), max_episode_steps=f.max_episode_steps,
                           imports=tuple(f.imports), paths=paths, setup=f.setup)  # fmt: skip
        if factory is not None:
            recipe = recipe.model_copy(update={"entry_point": factory.entry_point, "paths": tuple(dict.fromkeys(paths + factory.paths))})
        elif not builtin:
            recipe = _entry_point_recipe(recipe, where)
    names, descriptions, indices = _observed(f)
    bounds = f.bounds()
    spec = TaskSpec(
        name=f.name,
        env=recipe,
        observation=ObservationSpec(keys=None if f.observation.keys is None else tuple(f.observation.keys), indices=indices, names=names,
                                    descriptions=descriptions),
        action_type=f.action_type,
        actions=tuple(f.actions),
        components=_declared(f, "components"),
        diagnostics=_declared(f, "diagnostics"),
        recorder=f.recorder,
        summary=f.summary or "",
        reward_structure=f.reward_structure or "",
        reward_hint=f.reward_hint or "",
        hints=f.hints or "",
        optimal_return=f.optimal_return,
        complete=builtin,
        action_low=None if bounds is None else bounds[0],
        action_high=None if bounds is None else bounds[1],
        prompt_name=f.prompt_name,
        privacy=f.privacy,
        policy=_policy(f.policy, where),
    )
    if builtin:
        _check_complete(spec, where)
    return spec


def _policy(table: Mapping[str, Any] | None, where: str) -> PolicySpec | None:
    """A task file's ``[policy]`` table as a policy family (None for none or the linear one)."""
    if table is None:
        return None
    try:
        spec = parse_policy(table)
    except ValueError as e:
        raise TaskFileError(f"{where}: {e}") from None
    return None if spec.is_linear else spec


def with_policy(spec: TaskSpec, policy: PolicySpec) -> TaskSpec:
    """``spec`` searching the policy family ``policy`` (the linear one stores no ``policy`` key)."""
    return spec.model_copy(update={"policy": None if policy.is_linear else policy})


def _observed(f: TaskFile) -> tuple[tuple[str, ...], tuple[str, ...], tuple[int, ...] | None]:
    """(names, descriptions, indices) of the kept values, as far as the file says (the env may say the rest)."""
    obs = f.observation
    values = {k: v.strip() for k, v in obs.values.items()}
    names, descriptions = tuple(values), tuple(values.values())
    indices = obs.indices
    if obs.select is not None:
        indices = [names.index(n) for n in obs.select]
        names, descriptions = tuple(obs.select), tuple(values[n] for n in obs.select)
    elif indices is not None and names and len(names) != len(indices):
        names, descriptions = tuple(names[i] for i in indices), tuple(descriptions[i] for i in indices)
    return names, descriptions, None if indices is None else tuple(indices)


def _declared(f: TaskFile, kind: str) -> tuple[Declared, ...]:
    """The file's components or diagnostics; an info key defaults to the name (none without env, or with a recorder)."""
    table = f.components if kind == "components" else f.diagnostics
    out = []
    for name, e in table.items():
        by_code = f.env is None or f.recorder is not None or name in RESERVED
        info = e.info if e.info is not None else None if by_code else name
        reduce = e.reduce or ("sum" if kind == "components" else "last")
        out.append(Declared(name=str(name), description=e.description.strip(), info=info, reduce=reduce))
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
        recipe = recipe.model_copy(update={"paths": tuple(dict.fromkeys((*recipe.paths, root)))})
    if attr in gym.registry:
        return recipe  # the Gymnasium form module:EnvId
    if not callable(getattr(mod, attr.split(".")[0], None)):
        raise UnknownTaskError(f"{where}: module {module!r} has no env {attr!r} (neither an id it registers nor a class or "
                               "function returning an env)")  # fmt: skip
    return recipe.model_copy(update={"entry_point": recipe.id})


def _check_complete(spec: TaskSpec, where: str) -> None:
    obs = spec.observation
    if not obs.names or len(obs.names) != len(obs.descriptions):
        raise TaskFileError(f"{where}: a paper task must describe every observed value")
    if obs.indices is not None and len(obs.indices) != len(obs.names):
        raise TaskFileError(f"{where}: {len(obs.names)} observed values for {len(obs.indices)} indices")
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


# -- layout from the env's spaces ---------------------------------------------------------------
@cache
def _generic_text() -> dict[str, Any]:
    return tomllib.loads(resources.files(_TEXT).joinpath("generic.toml").read_text(encoding="utf-8"))


def _fmt(v: float) -> str:
    return f"{v:g}"


def _bounds(low: float, high: float) -> str:
    return _generic_text()["bounds"].format(low=_fmt(low), high=_fmt(high)) if np.isfinite(low) and np.isfinite(high) else ""


def _observation_layout(spec: TaskSpec, space: Any) -> tuple[OneHot | None, list[str], list[str]]:
    """One-hot of a Discrete observation, and a default (name, description) for every flattened value."""
    from gymnasium import spaces

    text = _generic_text()
    where = f"task {spec.name}"
    env_id = spec.env.id if spec.env is not None else spec.name
    keys = spec.observation.keys
    if isinstance(space, spaces.Dict):
        if keys is None:
            raise TaskFileError(f"{env_id} has a Dict observation ({', '.join(space.spaces)}); choose the entries the "
                                "policy sees with --obs-keys K1,K2 (or observation.keys in a task file)")  # fmt: skip
        names, descs = [], []
        for key in keys:
            if key not in space.spaces:
                close = difflib.get_close_matches(key, list(space.spaces), n=1)
                hint = f"; did you mean {close[0]}?" if close else ""
                raise TaskFileError(f"{where}: the Dict observation of {env_id} has no entry {key!r} "
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
    if keys is not None:
        raise TaskFileError(f"{where}: observation keys {', '.join(keys)} given, but {env_id} observes a "
                            f"{type(space).__name__}, not a Dict")  # fmt: skip
    if isinstance(space, spaces.Discrete):
        n, start = int(space.n), int(space.start)
        return OneHot(n=n, start=start), [f"state_{start + i}" for i in range(n)], [text["observation_one_hot"].format(index=start + i) for i in range(n)]
    if isinstance(space, (spaces.Box, spaces.MultiBinary)):
        size = int(np.prod(space.shape))
        lows = np.broadcast_to(np.asarray(getattr(space, "low", 0.0), dtype=float), space.shape).reshape(-1)
        highs = np.broadcast_to(np.asarray(getattr(space, "high", 1.0), dtype=float), space.shape).reshape(-1)
        return None, [f"obs_{i}" for i in range(size)], [text["observation"].format(index=i, bounds=_bounds(lows[i], highs[i]))
                                                          for i in range(size)]  # fmt: skip
    raise TaskFileError(f"{env_id} has a {type(space).__name__} observation; supported are Box, Discrete (one-hot) "
                        "and Dict of Box (choose entries with --obs-keys)")  # fmt: skip


def _action_layout(spec: TaskSpec, space: Any) -> tuple[str, list[str]]:
    from gymnasium import spaces

    text = _generic_text()
    env_id = spec.env.id if spec.env is not None else spec.name
    if isinstance(space, spaces.Discrete):
        if int(space.start) != 0:
            raise TaskFileError(f"{env_id}: Discrete actions starting at {space.start} are not supported")
        return "discrete", [text["action_discrete"].format(index=j) for j in range(int(space.n))]
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        lo, hi = np.asarray(space.low, dtype=float), np.asarray(space.high, dtype=float)
        return "continuous", [text["action_continuous"].format(index=j, bounds=_bounds(lo[j], hi[j])) for j in range(space.shape[0])]
    raise TaskFileError(f"{env_id}: only 1-D Box or Discrete action spaces are supported, got {space}")


# -- resolving: against the env's spaces, or as declared ---------------------------------------
def resolve(spec: TaskSpec) -> TaskSpec:
    """Complete a declaration: the counts, one-hot size and every description it left out.

    With an env: makes the env once and reads its observation and action spaces, which fill in
    what the declaration left out and must agree with what it gave; the env is closed unstepped
    (never reset, never stepped: on a real robot that would be a motion nobody asked for). Without
    env: the declaration itself gives every count. The feedback keys are checked by the episodes
    that use them (``feedback.InfoFeedback``) or by ``check.check_task``, never here.

    Raises:
        TaskFileError: the spaces disagree with the declaration; a ``KEY.*`` that needs a step of the
            env to be named (the message says how: ``ppprops task check``); a name declared twice.
        ConfigError (``envs.EnvError``, ``envs.TaskImportError``, ...): the env cannot be made (one line).
    """
    if spec.complete:
        return spec
    if spec.env is None:
        return finish_spec(spec)
    recipe = spec.env.pinned()
    spec = spec.model_copy(update={"env": recipe})
    env = recipe.make()
    try:
        spec = resolve_spaces(spec, env)
    finally:
        env.close()
    refuse_wildcards(spec)
    return finish_spec(spec)


def resolve_spaces(spec: TaskSpec, env: Any) -> TaskSpec:
    """``spec`` with its observation and action layout read from ``env``'s spaces (which it does not step)."""
    assert spec.env is not None
    env_id = spec.env.id
    one_hot, all_names, all_descs = _observation_layout(spec, env.observation_space)
    size = len(all_names)
    where = f"task {spec.name}"
    indices = spec.observation.indices
    if indices is not None:
        out = [i for i in indices if i >= size]
        if out:
            raise TaskFileError(f"{where}: observation index {out[0]} is out of range: the observation has {size} values (0-{size - 1})")
    kept = list(range(size)) if indices is None else list(indices)
    names, descs = spec.observation.names, spec.observation.descriptions
    if not names:
        names, descs = tuple(all_names[i] for i in kept), tuple(all_descs[i] for i in kept)
    elif len(names) == size and len(kept) != size:
        names, descs = tuple(names[i] for i in kept), tuple(descs[i] for i in kept)
    elif len(names) != len(kept):
        raise TaskFileError(f"{where}: observation.values describes {len(names)} values, but the policy sees {len(kept)} "
                            f"(of {size} in the observation)")  # fmt: skip
    action_type, action_descs = _action_layout(spec, env.action_space)
    if spec.action_type is not None and spec.action_type != action_type:
        raise TaskFileError(f"{where}: action_type is {spec.action_type}, but {env_id} has {action_type} actions")
    actions = spec.actions or tuple(action_descs)
    if len(actions) != len(action_descs):
        raise TaskFileError(f"{where}: actions describes {len(actions)} outputs, but {env_id} has {len(action_descs)}")
    observation = spec.observation.model_copy(update={"one_hot": one_hot, "names": tuple(names), "descriptions": tuple(descs)})
    return spec.model_copy(update={"observation": observation, "action_type": action_type, "actions": tuple(actions)})


def refuse_wildcards(spec: TaskSpec) -> None:
    """Refuse a ``KEY.*`` component or diagnostic: only a step of the env names its entries, and loading takes none."""
    if spec.recorder is not None:
        return
    for kind, declared in (("component", spec.components), ("diagnostic", spec.diagnostics)):
        for d in declared:
            if d.wildcard:
                assert d.info is not None
                flag = "--component" if kind == "component" else "--diagnostic"
                raise TaskFileError(
                    f"task {spec.name}: {kind} {d.info!r} asks for every entry of a dict in the env's info, which only a "
                    f"step of the env shows, and loading a task takes none: run `ppprops task check` with the same task "
                    f"and options (one zero-policy episode) to list them, then name each ({flag} {d.info[:-2]}.KEY)"
                )


def finish_spec(spec: TaskSpec) -> TaskSpec:
    """``spec`` (its counts known: resolved against the env's spaces, or without env) with generic text for
    whatever it leaves undescribed; complete. Raises TaskFileError for a name declared twice or reserved."""
    text = _generic_text()
    n_s, n_a = len(spec.observation.names), len(spec.actions)
    # the id of a public env (CartPole-v1) may be named; a user's module, class or task name may not
    summary = text["summary"].format(env_id=spec.env.id, n_s=n_s, n_a=n_a) if spec.env is not None and spec.public_env() \
        else text["summary_unnamed"].format(n_s=n_s, n_a=n_a)  # fmt: skip
    computed = tuple(d for d in spec.diagnostics if d.info is None)  # episode_length, a recorder's, a driver's
    declared = tuple(d for d in spec.diagnostics if d.info is not None)
    spec = spec.model_copy(update={
        "summary": spec.summary or summary.strip(),
        "reward_structure": spec.reward_structure or text["reward_structure"].strip(),
        "reward_hint": spec.reward_hint or text["reward_hint"].strip(),
        "hints": spec.hints or text.get("hints", "").strip(),
        "components": tuple(c.model_copy(update={"description": c.description or _component_text(c)}) for c in spec.components),
        "diagnostics": tuple(d.model_copy(update={"description": d.description or _diag_text(d)}) for d in (*computed, *declared)
                             if d.info is not None or d.description or spec.env is None),
        "complete": True,
    })  # fmt: skip
    _check_names(spec)
    return spec


def _component_text(c: Declared) -> str:
    return _generic_text()["component"].format(key=c.info or c.name)


def _diag_text(d: Declared) -> str:
    text = _generic_text()
    if d.reduce == "last":
        return text["diagnostic"].format(key=d.info or d.name)
    return text["diagnostic_reduced"].format(key=d.info or d.name, reduce=d.reduce)


def _check_names(spec: TaskSpec) -> None:
    names = [c.name for c in spec.components] + [d.name for d in spec.diagnostics]
    reserved = {d.name for d in (*spec.components, *spec.diagnostics) if d.name in RESERVED and d.info is not None}
    twice = sorted({n for n in names if names.count(n) > 1} | (reserved if spec.recorder is None else set()))
    if twice:
        raise TaskFileError(f"task {spec.name}: info key(s) declared twice or reserved: {', '.join(twice)}")
    if len(set(spec.observation.names)) != len(spec.observation.names):
        raise TaskFileError(f"task {spec.name}: two observed values share a name")


# -- building the Task -------------------------------------------------------------------------
def build_task(spec: TaskSpec) -> Task:
    """The Task the loop runs, from a declaration (resolved first when it is not complete; see ``resolve``)."""
    if not spec.complete:
        spec = resolve(spec)
    factory: Any
    if spec.recorder is not None:
        factory = load_attr(spec.recorder, f"task {spec.name}")
    else:
        factory = InfoFeedback(
            task=spec.name,
            components=tuple(InfoKey(c.name, c.info or c.name, "sum") for c in spec.components if spec.env is not None),
            diagnostics=tuple(InfoKey(d.name, d.info, d.reduce) for d in spec.diagnostics if d.info is not None),
        )
    counted = ("episode_length",) if spec.env is not None else ()  # ppprops counts the steps of the episodes it runs
    diag_names = tuple(dict.fromkeys((*counted, *(d.name for d in spec.diagnostics))))
    diag_text = {"episode_length": _generic_text()["diagnostics"]["episode_length"]} if counted else {}
    diag_text.update({d.name: d.description for d in spec.diagnostics if d.description})
    text = TaskText(
        summary=spec.summary,
        observations=spec.observation.descriptions,
        actions=spec.actions,
        reward_structure=spec.reward_structure,
        reward_hint=spec.reward_hint,
        hints=spec.hints,
        components={c.name: c.description for c in spec.components},
        diagnostics=diag_text,
    )
    assert spec.action_type is not None
    return Task(
        name=spec.name,
        env_id="" if spec.env is None else spec.env.id,
        n_s=len(spec.observation.names),
        n_a=len(spec.actions),
        action_type=spec.action_type,
        observation=spec.observation.selection(),
        feedback=factory,
        text=text,
        components=tuple(c.name for c in spec.components),
        diagnostics=diag_names,
        env_kwargs={} if spec.env is None else dict(spec.env.kwargs),
        optimal_return=spec.optimal_return,
        setup=NoEnv(spec.name) if spec.env is None else Prepare(spec.env),
        spec=spec,
        prompt_name=spec.prompt_name,
        action_low=spec.action_low,
        action_high=spec.action_high,
        policy=spec.policy or LINEAR,
    )


@cache
def _task_from_json_text(text: str) -> Task:
    return build_task(TaskSpec.model_validate(json.loads(text)))


def task_from_json(d: Mapping[str, Any]) -> Task:
    """The task of a stored declaration (``TaskSpec.model_dump(mode="json")``, of this or any earlier
    ppprops); one Task object per distinct declaration in a process.

    Raises TaskFileError when the declaration is damaged or of another format.
    """
    if not isinstance(d, Mapping) or d.get("format") != FORMAT:
        raise TaskFileError(f"stored task is not a {FORMAT} declaration")
    try:
        return _task_from_json_text(json.dumps(d, sort_keys=True))
    except ValidationError as e:
        err = e.errors(include_url=False)[0]
        where = ".".join(map(str, err["loc"]))
        raise TaskFileError(f"stored task declaration is damaged ({where}: {err['msg']})") from None
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        raise TaskFileError(f"stored task declaration is damaged ({type(e).__name__}: {e})") from None


__all__ = ["FORMAT", "Declared", "ObservationSpec", "OneHot", "TaskFileError", "TaskSpec", "build_task", "read_task_file", "finish_spec",
           "refuse_wildcards", "resolve", "resolve_spaces", "spec_for_env", "spec_from_table", "task_from_json", "with_policy"]  # fmt: skip
