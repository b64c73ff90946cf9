"""Names of runs and workers: run ids and default directories, one pattern for both (CleanRL's
``env__exp__seed__time``), and the plain names a study's workers go by.

A run started without ``--out`` lives in ``runs/<run id>``, so the id the summary prints is the
directory's name. Ids are ``<task>__<method>__<seed>__<YYYYmmdd-HHMMSS>-<4 hex digits>``: the
task's name with anything but letters, digits and ``_.+-`` replaced by ``_`` (a ``module:Env``
task has no ``:`` in its directory), and a random suffix so two runs started in the same second
never share one.
"""

from __future__ import annotations

import re
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import ConfigError

if TYPE_CHECKING:
    from .values import Trial

WORKER_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


def safe_name(text: str) -> str:
    """``text`` with every character but letters, digits and ``_.+-`` replaced by ``_`` (a file name)."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", text)


def new_run_id(task: str, method: str, seed: int) -> str:
    """A fresh run id (module docstring)."""
    return f"{safe_name(task)}__{method}__{seed}__{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:4]}"


def default_run_dir(config: Any, root: Path = Path("runs")) -> Path:
    """``root / new_run_id(...)`` for a run config (anything with ``task``, ``method`` and ``seed``)."""
    return Path(root) / new_run_id(str(config.task), str(config.method), int(config.seed))


def check_worker(name: str) -> str:
    """``name`` if it is a plain worker name (a letter or digit, then up to 63 letters, digits,
    ``.``, ``_`` or ``-``), else ConfigError."""
    if not isinstance(name, str) or not WORKER_NAME.fullmatch(name):
        raise ConfigError(f"worker name {name!r} is not a plain name: use letters, digits, '.', '_' and '-' "
                          "(up to 64, starting with a letter or digit), e.g. robot-2")
    return name


def holder(trial: Trial) -> str:
    """Who holds a trial that is out: its worker's name, ``unnamed worker`` or ``nobody yet``."""
    return "nobody yet" if trial.worker is None else (trial.worker or "unnamed worker")


def holders(trials: Sequence[Trial]) -> str:
    """``trial 3 (robot-1), trial 4 (nobody yet)``: which trials are out and who holds them."""
    return ", ".join(f"trial {t.number} ({holder(t)})" for t in trials)
