"""What a stored run is (``RunKind``) and where it stands (``RunStatus``).

Both are string enums whose values are exactly the strings stores have always held, so stores
written before these enums existed read back unchanged:

- kind: a search config carries no ``kind`` key (``search``); an RL baseline's carries ``"kind": "rl"``;
- status: ``running``, ``finished``, ``stopped: <reason>`` (a search that ended on purpose, e.g. a
  context overflow, and reports the best policy found before it) or ``interrupted`` (Ctrl-C).
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
    """Where a run stands. ``STOPPED`` is stored with its reason: ``"stopped: <reason>"``."""

    RUNNING = "running"
    FINISHED = "finished"
    STOPPED = "stopped"
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
        return f"{self.value}: {reason}" if (self is RunStatus.STOPPED and reason) else self.value

    def complete(self, kind: RunKind) -> bool:
        """Nothing left to do: finished, or (for a search) stopped on purpose. An RL run that did
        not finish cannot be continued, and an unfinished search is resumable."""
        return self is RunStatus.FINISHED or (self is RunStatus.STOPPED and kind is RunKind.SEARCH)


def is_complete(stored_status: str | None, kind: RunKind) -> bool:
    """``RunStatus.parse(stored_status)[0].complete(kind)``, for callers holding the stored text."""
    return RunStatus.parse(stored_status)[0].complete(kind)
