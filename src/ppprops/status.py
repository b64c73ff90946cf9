"""What a stored run is (``RunKind``) and where it stands (``RunStatus``).

Both are string enums whose values are exactly the strings stores have always held, so stores
written before these enums existed read back unchanged:

- kind: a search config carries no ``kind`` key (``search``); an RL baseline's carries ``"kind": "rl"``;
- status: ``running`` (a process runs the search: ``ppprops run``, ``resume``, ``search()``),
  ``open`` (a study driven by ask/tell, between its trials), ``finished``, ``stopped: <reason>``
  (a search that ended on purpose, e.g. a context overflow or a callback, and reports the best
  policy found before it), ``failed: <reason>`` (an error stopped it: the endpoint stayed down, the
  env raised; resumable) or ``interrupted`` (Ctrl-C, or a process that is gone; resumable).

A stored ``running`` is believed only while a process holds the run's lock
(``locks.RUNNING_LOCK``): ``effective`` turns it into ``interrupted`` when none does, so a run
killed with ``kill -9`` never shows as running.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import StrEnum
from typing import Any


class RunKind(StrEnum):
    """A search (warm-up, then a prompted or black-box search phase) or an RL baseline run."""

    SEARCH = "search"
    RL = "rl"

    @classmethod
    def of_config(cls, config: Mapping[str, Any]) -> RunKind:
        """The kind of a stored configuration (``RunStore.config()``); absent ``kind`` means a search."""
        return cls.RL if config.get("kind") == cls.RL.value else cls.SEARCH


class RunStatus(StrEnum):
    """Where a run stands. ``STOPPED`` and ``FAILED`` are stored with their reason: ``"stopped: <reason>"``."""

    RUNNING = "running"
    OPEN = "open"
    FINISHED = "finished"
    STOPPED = "stopped"
    FAILED = "failed"
    INTERRUPTED = "interrupted"
    UNKNOWN = "unknown"

    @classmethod
    def parse(cls, stored: str | None) -> tuple[RunStatus, str]:
        """``(status, reason)`` from a stored text; anything unrecognised is ``UNKNOWN``."""
        text = (stored or "").strip()
        head, _, reason = text.partition(":")
        try:
            return cls(head.strip()), reason.strip()
        except ValueError:
            return cls.UNKNOWN, text

    def stored(self, reason: str = "") -> str:
        """The text kept in the store: the value, with ``": reason"`` for a stopped run."""
        return f"{self.value}: {reason}" if (self in (RunStatus.STOPPED, RunStatus.FAILED) and reason) else self.value

    def complete(self, kind: RunKind) -> bool:
        """Nothing left to do: finished, or (for a search) stopped on purpose. An RL run that did
        not finish cannot be continued, and an unfinished search is resumable."""
        return self is RunStatus.FINISHED or (self is RunStatus.STOPPED and kind is RunKind.SEARCH)


def effective(stored_status: str | None, run_dir: Any) -> tuple[RunStatus, str]:
    """``(status, reason)`` of a run as it is now: a stored ``running`` becomes ``interrupted``
    ("no process is running it") when no process holds the run's lock in ``run_dir``."""
    status, reason = RunStatus.parse(stored_status)
    if status is RunStatus.RUNNING:
        from .locks import RUNNING_LOCK, held

        if not held(run_dir, RUNNING_LOCK):
            return RunStatus.INTERRUPTED, "no process is running it"
    return status, reason


def is_complete(stored_status: str | None, kind: RunKind) -> bool:
    """``RunStatus.parse(stored_status)[0].complete(kind)``, for callers holding the stored text."""
    return RunStatus.parse(stored_status)[0].complete(kind)
