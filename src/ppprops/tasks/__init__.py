"""Task registry: look tasks up by the paper's name (or any Gymnasium id, in a later extension)."""

from __future__ import annotations

import difflib

from ..errors import UnknownTaskError
from .base import ComponentSums, EpisodeFeedback, EpisodeRecorder, FlatBox, Task, TaskText
from .classic import TASKS as _CLASSIC

_REGISTRY: dict[str, Task] = {}


def register(task: Task) -> Task:
    """Add a task; its name and env id must not clash with one already registered."""
    if task.name.lower() in _REGISTRY:
        raise ValueError(f"task {task.name!r} is already registered")
    _REGISTRY[task.name.lower()] = task
    return task


for _t in _CLASSIC:
    register(_t)


def list_tasks() -> list[Task]:
    return list(_REGISTRY.values())


def get_task(name: str) -> Task:
    """Find a task by its name (case-insensitive) or by its env id when that id names one task only."""
    key = name.lower()
    if key in _REGISTRY:
        return _REGISTRY[key]
    by_id = [t for t in _REGISTRY.values() if t.env_id.lower() == key]
    if len(by_id) == 1:
        return by_id[0]
    names = [t.name for t in _REGISTRY.values()]
    close = difflib.get_close_matches(name, names + [t.env_id for t in _REGISTRY.values()], n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else f"; known tasks: {', '.join(names)}"
    raise UnknownTaskError(f"unknown task {name!r}{hint}")


__all__ = [
    "ComponentSums",
    "EpisodeFeedback",
    "EpisodeRecorder",
    "FlatBox",
    "Task",
    "TaskText",
    "get_task",
    "list_tasks",
    "register",
]
