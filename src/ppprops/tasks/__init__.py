"""Task registry: look tasks up by the paper's name, or by any Gymnasium id (a generic task).

Registering a task imports nothing heavy: simulators are imported when a task's env is made, so the
list of tasks is available without any extra installed.
"""

from __future__ import annotations

import difflib

from ..errors import UnknownTaskError
from .base import ComponentSums, EpisodeFeedback, EpisodeRecorder, FlatBox, Task, TaskText
from .classic import TASKS as _CLASSIC
from .generic import GenericSpec, generic_task, known_ids, registered_id, spec_of
from .highway import PRESETS as _HIGHWAY_PRESETS
from .highway import TASKS as _HIGHWAY
from .mujoco import TASKS as _MUJOCO
from .robotics import TASKS as _ROBOTICS

_REGISTRY: dict[str, Task] = {}
_NAME_ONLY: set[str] = set()  # tasks an env id never resolves to (presets sharing a paper task's env)


def register(task: Task, *, by_env_id: bool = True) -> Task:
    """Add a task; its name must not clash with one already registered.

    ``by_env_id=False`` keeps ``get_task(env_id)`` pointing at the main task of that env.
    """
    if task.name.lower() in _REGISTRY:
        raise ValueError(f"task {task.name!r} is already registered")
    _REGISTRY[task.name.lower()] = task
    if not by_env_id:
        _NAME_ONLY.add(task.name.lower())
    return task


for _t in (*_MUJOCO, *_CLASSIC, *_ROBOTICS, *_HIGHWAY):
    register(_t)
for _t in _HIGHWAY_PRESETS:
    register(_t, by_env_id=False)


def list_tasks() -> list[Task]:
    return list(_REGISTRY.values())


def get_task(name: str) -> Task:
    """Find a task by its name (case-insensitive), by its env id, or build one for a Gymnasium id.

    An env id that several tasks share (Ant-v5: Ultra, Joints, Torso) is an error naming them; an
    id no task uses gives a generic task (see ``generic_task``).
    """
    key = name.lower()
    if key in _REGISTRY:
        return _REGISTRY[key]
    by_id = [t for k, t in _REGISTRY.items() if t.env_id.lower() == key and k not in _NAME_ONLY]
    if len(by_id) == 1:
        return by_id[0]
    if by_id:
        raise UnknownTaskError(f"{name!r} is the env of several tasks; pick one: {', '.join(t.name for t in by_id)}")
    if registered_id(name) is not None:
        return generic_task(name)
    names = [t.name for t in _REGISTRY.values()]
    candidates = names + [t.env_id for t in _REGISTRY.values()] + known_ids()
    close = difflib.get_close_matches(name, list(dict.fromkeys(candidates)), n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else f"; known tasks: {', '.join(names)}"
    raise UnknownTaskError(f"unknown task {name!r}{hint}")


TaskRef = str | GenericSpec | Task


def task_ref(task: Task) -> TaskRef:
    """A small picklable handle from which another process rebuilds ``task`` (see ``resolve_task``)."""
    spec = spec_of(task)
    if spec is not None:
        return spec
    if _REGISTRY.get(task.name.lower()) is task:
        return task.name
    return task  # an ad-hoc task: sent whole, so it must pickle


def resolve_task(ref: TaskRef) -> Task:
    if isinstance(ref, str):
        return get_task(ref)
    if isinstance(ref, GenericSpec):
        return generic_task(ref.env_id, ref.components, ref.diagnostics)
    return ref


__all__ = [
    "ComponentSums",
    "EpisodeFeedback",
    "EpisodeRecorder",
    "FlatBox",
    "GenericSpec",
    "Task",
    "TaskRef",
    "TaskText",
    "generic_task",
    "get_task",
    "list_tasks",
    "register",
    "resolve_task",
    "task_ref",
]
