"""Reaching the model: the one LLM protocol, the endpoint client, the recording client and the embedded server.

The names below load with ``llm.protocol`` on first use: the settings (``llm.settings``) need none of them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .protocol import LLM, Exchange, LLMRejected, LLMUnavailable

__all__ = ["LLM", "Exchange", "LLMRejected", "LLMUnavailable"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import protocol

        return getattr(protocol, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
