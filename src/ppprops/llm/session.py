"""An LLM client for the length of a study: the configured endpoint, or the embedded model started
when the first request needs it.

``open_client`` makes the ``ChatClient`` of an ``LLMConfig`` (starting the shipped llama.cpp
server for the embedded model) and closes it afterwards; ``LazyChat`` defers that to the first
request, so a warm-up never waits for a model to load, and holds a grid's gate around each
request. Neither records anything: the study wraps them in the recording client
(``llm.recording.RecordingChat``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import AbstractContextManager, ExitStack, contextmanager, nullcontext

from ..errors import ConfigError
from .client import ChatClient, Exchange, RequestShape
from .settings import LLMConfig

CHAT_TEMPLATE_MARGIN = 32  # tokens the chat template adds around a single user message


def _ignore(*args: object) -> None:
    return None


def api_key(llm: LLMConfig) -> str:
    """The API key from the environment variable ``llm.api_key_env`` ("not-needed" when none is
    named). Raises ConfigError when the named variable is empty or unset, before anything is sent."""
    if not llm.api_key_env:
        return "not-needed"
    key = os.environ.get(llm.api_key_env, "")
    if not key:
        raise ConfigError(f"--api-key-env names {llm.api_key_env}, but that environment variable is empty or unset")
    return key


@contextmanager
def open_client(llm: LLMConfig, *, on_loading: Callable[[], None] = _ignore,
                on_ready: Callable[[float], None] = _ignore) -> Iterator[ChatClient]:
    """The configured endpoint's client, or the embedded llama.cpp server started for the duration
    (``on_loading()`` before, ``on_ready(seconds)`` after its start). Raises ConfigError when the
    named API-key variable is empty, LLMError when the embedded server fails to start."""
    with ExitStack() as stack:
        if llm.embedded:
            from .embedded import EmbeddedServer

            on_loading()
            t0 = time.monotonic()
            server = stack.enter_context(EmbeddedServer(context_size=llm.context_size))
            on_ready(time.monotonic() - t0)
            client = ChatClient(llm, base_url=server.base_url, api_key="not-needed", shape=RequestShape.for_config(llm))
        else:
            key = api_key(llm)
            assert llm.base_url is not None and llm.model is not None
            client = ChatClient(llm, base_url=llm.base_url, api_key=key, shape=RequestShape.for_config(llm))
        try:
            yield client
        finally:
            client.close()


class LazyChat:
    """Starts the LLM only when the first request needs it, so the warm-up never waits for it.

    ``gate`` (e.g. a grid's semaphore) is held around every request; ``on_loading`` and
    ``on_ready(seconds)`` are called around the embedded model's start.
    """

    def __init__(self, llm: LLMConfig, gate: AbstractContextManager[object] | None = None, *,
                 on_loading: Callable[[], None] = _ignore, on_ready: Callable[[float], None] = _ignore) -> None:  # fmt: skip
        self.llm = llm
        self.gate = gate if gate is not None else nullcontext()
        self._on_loading, self._on_ready = on_loading, on_ready
        self._stack = ExitStack()
        self._client: ChatClient | None = None

    def _get(self) -> ChatClient:
        if self._client is None:
            self._client = self._stack.enter_context(open_client(self.llm, on_loading=self._on_loading, on_ready=self._on_ready))
        return self._client

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        """``ChatClient.complete`` on the client started on first use, holding the gate."""
        client = self._get()
        with self.gate:
            return client.complete(messages, D=D, seed=seed)

    def complete_document(self, prompt: str, *, D: int, seed: int | None = None, grammar: str | None = None,
                          temperature: float | None = None, sampling: Mapping[str, float] | None = None) -> Exchange:
        """Continue a document-form ``prompt`` (``ChatClient.complete_document``), starting the endpoint on first use."""
        client = self._get()
        with self.gate:
            return client.complete_document(prompt, D=D, seed=seed, grammar=grammar, temperature=temperature, sampling=sampling)

    def count_tokens(self, text: str) -> int:
        """A local estimate, nothing sent: one token per two characters (digit-heavy prompts tokenize
        densely; no tokenizer of the endpoint's model is known here). R2PO refines this with the
        usage counts of its answers."""
        return len(text) // 2 + CHAT_TEMPLATE_MARGIN

    def close(self) -> None:
        """Close the client (and stop the embedded server) if one was started."""
        self._stack.close()
