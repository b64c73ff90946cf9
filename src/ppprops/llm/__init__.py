"""Reaching a model: any OpenAI-compatible endpoint, or the embedded llama.cpp server."""

from .client import ChatClient, Exchange

__all__ = ["ChatClient", "Exchange"]
