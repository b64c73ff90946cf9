"""Reaching the model: the one LLM protocol, the endpoint client, the recording client and the embedded server."""

from .protocol import LLM, Exchange, LLMRejected, LLMUnavailable

__all__ = ["LLM", "Exchange", "LLMRejected", "LLMUnavailable"]
