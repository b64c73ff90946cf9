"""Proposers speak ask/tell; the study (``ppprops.study``) evaluates, records and reports for all of them.

The names below load with their module on first use: the study's phases import only the proposers
they run (``proposers.base`` alone costs no prompt builder or LLM client).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .base import Proposal, Proposer
    from .llm import LLMProposer
    from .uniform import UniformSampler

_MODULES = {"Proposal": "base", "Proposer": "base", "LLMProposer": "llm", "UniformSampler": "uniform"}

__all__ = ["LLMProposer", "Proposal", "Proposer", "UniformSampler"]


def __getattr__(name: str) -> Any:
    if name in _MODULES:
        from importlib import import_module

        return getattr(import_module(f".{_MODULES[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
