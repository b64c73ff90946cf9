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


class MissingExtraError(PPPropsError, ImportError):
    """An optional dependency group is not installed; the message names the pip extra."""

    def __init__(self, extra: str, what: str) -> None:
        super().__init__(f"{what} needs the '{extra}' extra: pip install 'ppprops[{extra}]'")
        self.extra = extra
