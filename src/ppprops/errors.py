"""One exception root, so the CLI can turn any expected failure into a one-line message and exit 2."""

from __future__ import annotations


class PPPropsError(Exception):
    """Root of every error ppprops raises on purpose (bad input, bad files, exhausted retries)."""


class ConfigError(PPPropsError, ValueError):
    """A setting, flag or spec value is out of range or inconsistent."""


class UnknownTaskError(ConfigError):
    """The task name is neither a ppprops task nor a registered Gymnasium id."""


class StoreError(PPPropsError):
    """The run store or run directory is missing, corrupt, or belongs to another run."""


class KeyFileError(PPPropsError):
    """The secret key file is missing, unreadable, corrupt, or does not match its run."""


class LLMError(PPPropsError):
    """The LLM endpoint could not be reached or kept failing past the retry bound."""


class StudyComplete(ConfigError):
    """``Study.ask`` after the budget is spent (or after the search stopped on purpose): finalize
    instead. ``finalized``: the study is already finalized (nothing left to do)."""

    def __init__(self, message: str, *, finalized: bool = False) -> None:
        super().__init__(message)
        self.finalized = finalized


class TrialsOut(ConfigError):
    """``Study.ask`` cannot hand out a trial now: ``--parallel`` trials are out, or a round, a phase
    or a CMA-ES generation waits for trials that are out (``ppprops ask`` exits 4 with this line).
    ``out``: how many trials are out."""

    def __init__(self, message: str, *, out: int) -> None:
        super().__init__(message)
        self.out = out


class MissingExtraError(PPPropsError, ImportError):
    """An optional dependency group is not installed; the message names the pip extra."""

    def __init__(self, extra: str, what: str) -> None:
        super().__init__(f"{what} needs the '{extra}' extra: pip install 'ppprops[{extra}]'")
        self.extra = extra


def interrupted_by_user(error: BaseException) -> bool:
    """Whether a Ctrl-C lies under ``error``: a ``KeyboardInterrupt`` itself, or one that Python
    wrapped on its way up. A SIGINT that lands while a module is being imported lazily (an HTTP
    client loading its resources on first use) can surface as ``RuntimeError: Error calling
    __set_name__ ...`` whose cause is the ``KeyboardInterrupt`` (Python 3.11); such an error means
    the user stopped the run, not that the run failed. Follows ``__cause__`` and ``__context__``."""
    seen: set[int] = set()
    e: BaseException | None = error
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False
