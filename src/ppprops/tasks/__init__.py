"""Task registry and loading: the paper's task files, a user's task files, Gymnasium ids, env factories.

``get_task(name)`` finds a task by its name, its env id, a task file path, or builds one for any
Gymnasium id. ``load_task(source, options=...)`` is the general form behind ``ppprops run`` and
``ppprops.search``: the source may also be an env factory or a ``TaskSpec``, with the quick options
of a ``tasks.options.TaskOptions`` (env kwargs, a step limit, packages to import, Dict keys, info keys)
applied.

The registry reads the paper's task files the first time it is used (importing ``ppprops.tasks``
reads none); simulators are imported when a task's env is made, so the list of tasks is available
without any extra installed. Loading a task makes its env at most once, to read its spaces, and
never steps it; ``check_task`` runs the one zero-policy episode that checks a declaration, when the
user asks for it (``ppprops task check``).
"""

from __future__ import annotations

import difflib
import os
import threading
from collections.abc import Callable, Mapping
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ConfigError, UnknownTaskError
from .base import EpisodeFeedback, EpisodeRecorder, NoEnvError, Selection, Task, TaskText
from .check import PROBE_STEPS, TaskCheck, check_spec
from .envs import EnvError, EnvRecipe, TaskImportError, describe_user_error, import_module, known_ids, registered_id
from .facts import PrivacyFacts
from .feedback import FeedbackKeyError
from .paper import PRESET_FILES, TASK_FILES
from .spec import (
    Declared,
    TaskFileError,
    TaskSpec,
    build_task,
    read_task_file,
    resolve,
    spec_for_env,
    spec_from_table,
    task_from_json,
)

if TYPE_CHECKING:
    from .options import TaskOptions

_REGISTRY: dict[str, Task] = {}  # read through _tasks(): the paper's tasks are read into it on first use
_NAME_ONLY: set[str] = set()  # tasks an env id never resolves to (presets sharing a paper task's env)
_BUILTIN: set[str] = set()  # the paper's tasks: always known by name, in every process
_PAPER_READ = False
_LOCK = threading.Lock()


def _tasks() -> dict[str, Task]:
    """The registry, with the paper's tasks read into it the first time it is used (so importing
    ``ppprops.tasks`` reads no task file and builds no validator)."""
    global _PAPER_READ
    if not _PAPER_READ:
        with _LOCK:
            if not _PAPER_READ:
                _load_paper()
                _PAPER_READ = True
    return _REGISTRY


def register(task: Task | TaskSpec | Mapping[str, Any] | str | os.PathLike[str], *, by_env_id: bool = True) -> Task:
    """Add a task (a Task, a TaskSpec, a task-file table as a dict, or a task file path) so ``get_task`` finds it by name.

    The name must not clash with a task already registered, unless it is the same declaration.
    ``by_env_id=False`` keeps ``get_task(env_id)`` pointing at the main task of that env.
    A registered task is known in this process only; runs store its declaration, so resuming
    or evaluating them elsewhere needs no registration.

    Raises:
        ValueError (ConfigError): the name is taken by another declaration.
    """
    registry = _tasks()
    if not isinstance(task, Task):
        task = load_task(task)
    return _add(registry, task, by_env_id)


def _add(registry: dict[str, Task], task: Task, by_env_id: bool) -> Task:
    key = task.name.lower()
    old = registry.get(key)
    if old is not None:
        if old is task or (old.spec is not None and task.spec is not None
                           and old.spec.model_dump(mode="json") == task.spec.model_dump(mode="json")):  # fmt: skip
            return old
        raise ConfigError(f"task {task.name!r} is already registered")
    registry[key] = task
    if not by_env_id:
        _NAME_ONLY.add(key)
    return task


def _load_paper() -> None:
    root = resources.files(__name__ + ".paper")
    for files, by_env_id in ((TASK_FILES, True), (PRESET_FILES, False)):
        for filename in files:
            with resources.as_file(root.joinpath(filename)) as path:
                task = build_task(read_task_file(path, builtin=True))
            _add(_REGISTRY, task, by_env_id)
            _BUILTIN.add(task.name.lower())


def list_tasks() -> list[Task]:
    """Every registered task: the paper's ten and its presets first, then any registered in this process."""
    return list(_tasks().values())


def is_builtin(task: Task) -> bool:
    """True for the paper's own task objects (known by name in every process)."""
    return task.name.lower() in _BUILTIN and _tasks().get(task.name.lower()) is task


def registered(name: str) -> Task | None:
    """The task registered in this process under ``name`` (case-insensitive), or None; makes no env (the
    paper's task files are read the first time any registry function is called)."""
    return _tasks().get(name.lower())


def privacy_facts(task: Task | TaskSpec) -> PrivacyFacts:
    """The privacy facts a task declares (``tasks.facts.PrivacyFacts``), read from its declaration.

    A declaration stored before privacy facts existed (no ``privacy`` key) is given the facts of the
    paper task of the same name when it is that task's declaration in every other respect (a run of
    a paper task from an earlier ppprops), and none otherwise. A Task made by hand has none.
    """
    spec = task.spec if isinstance(task, Task) else task
    if spec is None:
        return PrivacyFacts()
    if spec.privacy is not None:
        return spec.privacy
    paper = _tasks().get(spec.name.lower())
    if paper is not None and is_builtin(paper) and paper.spec is not None:
        mine, theirs = (s.model_dump(mode="json", exclude={"privacy"}) for s in (spec, paper.spec))
        if mine == theirs and paper.spec.privacy is not None:
            return paper.spec.privacy
    return PrivacyFacts()


def _is_task_file(name: str) -> bool:
    return name.lower().endswith(".toml")


def get_task(name: str) -> Task:
    """Find a task by its name (case-insensitive), its env id, a task file path, or build one for a Gymnasium id.

    An env id that several tasks share (Ant-v5: Ultra, Joints, Torso) is an error naming them; an
    id no task uses gives a generic task (see ``generic_task``); a path ending in ``.toml`` is read
    as a task file and registered.

    Raises:
        UnknownTaskError: neither a task, a task file, nor a Gymnasium id (with close matches).
        ConfigError: the task file or the env's info keys are wrong (one line naming the cause).
    """
    key = name.lower()
    registry = _tasks()
    if key in registry:
        return registry[key]
    by_id = [t for k, t in registry.items() if t.env_id and t.env_id.lower() == key and k not in _NAME_ONLY]
    if len(by_id) == 1:
        return by_id[0]
    if by_id:
        raise UnknownTaskError(f"{name!r} is the env of several tasks; pick one: {', '.join(t.name for t in by_id)}")
    if _is_task_file(name):
        return register(name)
    found = registered_id(name)
    if found is not None or ":" in name:  # module:attr: an env class or factory (checked when built)
        return generic_task(found or name)
    names = [t.name for t in registry.values()]
    candidates = names + [t.env_id for t in registry.values()] + known_ids()
    close = difflib.get_close_matches(name, list(dict.fromkeys(candidates)), n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else f"; known tasks: {', '.join(names)}"
    raise UnknownTaskError(f"unknown task {name!r}{hint}")


def generic_task(
    env_id: str, components: tuple[str, ...] | list[str] = (), diagnostics: tuple[str, ...] | list[str] = ()
) -> Task:
    """A Task for any registered Gymnasium id with a Box (or Discrete, one-hot) observation and Box/Discrete actions.

    ``components`` are info keys summed over an episode and reported as reward components (they are
    scaled with the return under PP-ProPS, so declare only reward-valued keys); ``diagnostics`` are
    info keys reported as their last value, never scaled. Making the task makes the env once to
    read its spaces, never steps it: the keys are checked by the episodes that use them, or by
    ``check_task``.
    """
    return _generic(env_id, tuple(components), tuple(diagnostics))


@cache
def _generic(name: str, components: tuple[str, ...], diagnostics: tuple[str, ...]) -> Task:
    from .options import TaskOptions

    found = registered_id(name)
    if found is None and ":" not in name:
        raise UnknownTaskError(f"unknown task {name!r}: not a registered Gymnasium id")
    spec = spec_for_env(found or name).with_options(TaskOptions(components=components, diagnostics=diagnostics))
    return build_task(resolve(spec))


TaskSource = str | os.PathLike[str] | Callable[..., Any] | Mapping[str, Any] | TaskSpec | Task


def load_task(source: TaskSource | None = None, *, task_file: str | os.PathLike[str] | None = None, options: TaskOptions | None = None) -> Task:
    """The task a run searches, from any of the forms a user gives one in.

    ``source`` is a paper task name (``"Ant-Ultra"``), a Gymnasium id (``"Pendulum-v1"``), a
    ``module:EnvId`` or ``module:attr`` string (an Env class or a function returning an env), a path
    to a task file (``.toml``), a dict with a task file's keys (``{"name": ..., "env": ...,
    "observation": {"indices": [...]}}``), an env factory callable, a ``TaskSpec``, or a ``Task``;
    ``task_file`` names a task file instead. ``options`` (a ``ppprops.tasks.options.TaskOptions``) holds
    the options of ``ppprops run`` (``--env-kwargs``, ``--max-episode-steps``, ``--gym-packages``,
    ``--obs-keys``, ``--component``, ``--diagnostic``), which win over the declaration; its ``env``
    or ``task_file`` names the task when neither ``source`` nor ``task_file`` does
    (``load_task(options=TaskOptions(env="Pendulum-v1", max_episode_steps=100))``). A task that is
    not a paper task is checked against its env's observation and action spaces (the env is made,
    never stepped); its feedback keys are checked by the episodes that use them, or by
    ``check_task`` when asked. A task file without ``env`` gives a task without env
    (``Task.has_env`` False), driven with ask/tell.

    Raises:
        UnknownTaskError, TaskFileError, TaskImportError, EnvError (all ConfigError): one line naming
        what is wrong (an unknown id, a bad task file, a module that fails to import and why, an env
        whose constructor raises, a ``KEY.*`` that only ``check_task`` can expand).
    """
    found = _source(source, task_file, options)
    return _with_policy(found if isinstance(found, Task) else build_task(resolve(found)), options)


def _with_policy(task: Task, options: TaskOptions | None) -> Task:
    """``task`` searching the policy family ``options`` choose (``--policy`` / ``--activation``), a paper
    task too; ``task`` itself when they choose none or the one it declares.

    Raises:
        ConfigError: ``--activation`` without an mlp, or a Task made by hand (no declaration to change).
    """
    if options is None or (options.policy is None and options.activation is None):
        return task
    from ..policy import parse_policy
    from .spec import with_policy

    try:
        policy = parse_policy(options.policy if options.policy is not None else task.policy, options.activation)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if policy == task.policy:
        return task
    if task.spec is None:
        raise ConfigError(f"task {task.name} is a Task made by hand: give its policy family in its declaration (TaskSpec.policy)")
    return build_task(with_policy(task.spec, policy))


def check_task(source: TaskSource | None = None, *, task_file: str | os.PathLike[str] | None = None, options: TaskOptions | None = None,
               seed: int = 0, max_steps: int = PROBE_STEPS) -> TaskCheck:  # fmt: skip
    """Check a task in one zero-policy episode on its env and report every problem (``ppprops task check``).

    The task is named as for ``load_task`` (same ``source`` forms and ``options``). The episode is
    reset with ``seed`` and runs at most ``max_steps`` steps. ``KEY.*`` components and diagnostics
    are expanded here, and only here: ``result.expanded`` lists their entries, and
    ``result.checked`` is the task with them named (None when the check found problems), ready for
    ``ppprops.search``. A task without env is validated and needs no episode.

    Raises:
        ConfigError: one line for what stops the check before the episode (an unknown task, a bad
            task file, an env that cannot be made, spaces that disagree with the declaration); what
            the episode finds is in ``result.problems`` instead.
    """
    found = _source(source, task_file, options)
    if isinstance(found, Task):
        if found.spec is None:
            raise ConfigError(f"task {found.name} is a Task made by hand, with no declaration to check")
        found = found.spec
    if options is not None and (options.policy is not None or options.activation is not None):
        from ..policy import LINEAR, parse_policy
        from .spec import with_policy

        try:
            found = with_policy(found, parse_policy(options.policy or found.policy or LINEAR, options.activation))
        except ValueError as e:
            raise ConfigError(str(e)) from None
    return check_spec(found, seed=seed, max_steps=max_steps)


def _source(source: TaskSource | None, task_file: str | os.PathLike[str] | None, options: TaskOptions | None) -> Task | TaskSpec:
    """The registered Task a source names, or the declaration (options applied, not yet resolved) it gives."""
    given = options is not None and options.has_options
    if options is not None and (options.env is not None or options.task_file is not None):
        if source is not None or task_file is not None:
            raise ConfigError("the task is named twice: give it as the source or in the options (env / task_file), not both")
        source, task_file = options.env, options.task_file
    for module in options.gym_packages if options is not None else ():
        import_module(module, "--gym-packages")
    if task_file is not None:
        if source is not None:
            raise ConfigError("give a task name/id or a task file, not both (--env or --task-file)")
        source = Path(task_file)
    if source is None:
        raise ConfigError("no task: give a task name or Gymnasium id (--env), or a task file (--task-file)")
    spec: TaskSpec
    if isinstance(source, Task):
        if given:
            raise ConfigError(f"task {source.name} is a Task object: change its declaration (its .spec) instead of passing options")
        return source
    if isinstance(source, TaskSpec):
        spec = source
    elif isinstance(source, Mapping):
        spec = spec_from_table(dict(source), where=f"task {source.get('name', '?')!r}")
    elif isinstance(source, os.PathLike) or (isinstance(source, str) and _is_task_file(source)):
        spec = read_task_file(Path(source))
    elif isinstance(source, str):
        if not given:
            return get_task(source)
        registry = _tasks()
        known = registry.get(source.lower())
        if known is None:
            by_id = [t for k, t in registry.items() if t.env_id and t.env_id.lower() == source.lower() and k not in _NAME_ONLY]
            known = by_id[0] if len(by_id) == 1 else None
        if known is not None and is_builtin(known):
            if known.name.lower() == source.lower():
                raise ConfigError(f"{known.name} is a paper task: its env, observation and feedback are fixed; to change them, "
                                  f"write a task file (docs/own-robot.md) or give its env id {known.env_id}")  # fmt: skip
            known = None  # the paper task's env id: a generic task of that env, with the options
        if known is not None and known.spec is not None:
            spec = known.spec
        else:
            if ":" not in source:
                found = registered_id(source)
                if found is None:
                    get_task(source)  # the unknown-task error, with close matches
                source = found or source
            spec = spec_for_env(source)
    elif callable(source):
        spec = spec_for_env(source)
    else:
        raise ConfigError(f"a task is a name, a Gymnasium id, a task file, an env factory, a TaskSpec or a Task; got {source!r}")
    if given:
        assert options is not None
        spec = spec.with_options(options)
    return spec


TaskRef = str | dict[str, Any] | Task


def task_ref(task: Task) -> TaskRef:
    """A small picklable handle from which another process rebuilds ``task`` (see ``resolve_task``).

    A paper task is its name; a task with a declaration is that declaration (JSON values, so the
    other process needs none of the code that registered it); a hand-made Task is sent whole.
    """
    if is_builtin(task):
        return task.name
    if task.spec is not None:
        return task.spec.model_dump(mode="json")
    return task  # an ad-hoc task: sent whole, so it must pickle


def resolve_task(ref: TaskRef) -> Task:
    """The task a ``task_ref`` handle stands for (in any process)."""
    if isinstance(ref, str):
        return get_task(ref)
    if isinstance(ref, dict):
        return task_from_json(ref)
    return ref


__all__ = [
    "Declared",
    "EnvError",
    "EnvRecipe",
    "EpisodeFeedback",
    "EpisodeRecorder",
    "FeedbackKeyError",
    "NoEnvError",
    "PrivacyFacts",
    "Selection",
    "Task",
    "TaskCheck",
    "TaskFileError",
    "TaskImportError",
    "TaskRef",
    "TaskSpec",
    "TaskText",
    "check_task",
    "describe_user_error",
    "generic_task",
    "get_task",
    "is_builtin",
    "list_tasks",
    "load_task",
    "privacy_facts",
    "read_task_file",
    "register",
    "registered",
    "resolve_task",
    "task_from_json",
    "task_ref",
]
