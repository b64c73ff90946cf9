"""An offline stand-in for the LLM, so audits and attacks can be exercised on many runs quickly.

``EchoOptimizer`` answers each prompt the way a simple optimizer in the encoded space would: it
reads the best history entry (last in the prompt) and perturbs it with Gaussian noise scaled to
each coordinate's magnitude. It sees exactly what a provider sees, so its transcripts have the
structure of real ones (warm-up first, LLM answers that may leave the box and get clipped).
``offline_llm()`` makes the runner use it in place of the configured endpoint.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from ..llm.client import Exchange
from ..wire.transcript import history_entries


class EchoOptimizer:
    """Chat protocol (both prompt forms): best shown entry + N(0, spread * (|x| + 1)) per coordinate, two decimals."""

    def __init__(self, config: Any = None, *, spread: float = 0.5) -> None:
        self.spread = spread
        self.calls = 0
        self.config = config

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        """Answer a chat request: ``{"params": [...]}`` with D numbers, from the history entries of the
        first message (the prompt); zeros plus noise when it shows none of length D. ``seed`` fixes
        the noise. The Exchange's request is the body the run's client would send (latency 0)."""
        self.calls += 1
        prompt = messages[0]["content"]
        proposal = self._propose(history_entries(prompt, "chat"), D, seed)
        content = json.dumps({"params": [round(float(v), 2) for v in proposal]})
        body = self._body(messages, D, seed)
        return Exchange(request=json.dumps(body), response=None, content=content, reasoning=None,
                        prompt_chars=sum(len(m["content"]) for m in messages), prompt_tokens=None, completion_tokens=None,
                        latency_s=0.0, ok=True)

    def complete_document(self, prompt: str, *, D: int, seed: int | None = None, grammar: str | None = None,
                          temperature: float | None = None, sampling: dict[str, float] | None = None) -> Exchange:
        """The document form: the same proposal, written as the continuation of the open list."""
        self.calls += 1
        proposal = self._propose(history_entries(prompt, "document"), D, seed)
        content = ",".join(f"{i}:{v:.2f}" for i, v in enumerate(proposal)) + "]"
        body = self._body(None, D, seed, prompt=prompt, grammar=grammar, temperature=temperature, sampling=sampling)
        return Exchange(request=json.dumps(body), response=None, content=content, reasoning=None, prompt_chars=len(prompt),
                        prompt_tokens=None, completion_tokens=None, latency_s=0.0, ok=True, finish_reason="stop")

    def _propose(self, entries: list, D: int, seed: int | None) -> np.ndarray:  # type: ignore[type-arg]
        rng = np.random.default_rng(seed)
        if entries and len(entries[-1].params) == D:
            best = np.array([float(t) for t in entries[-1].params])
        else:
            best = np.zeros(D)
        return best + rng.normal(0.0, self.spread * (np.abs(best) + 1.0))

    def _body(self, messages: list[dict[str, str]] | None, D: int, seed: int | None, *, prompt: str | None = None,
              grammar: str | None = None, temperature: float | None = None, sampling: dict[str, float] | None = None) -> dict[str, Any]:
        """The body a fresh client of the run's endpoint would send (so the audit reads a real one):
        a chat body for ``messages``, a completions body for a document ``prompt``."""
        if self.config is None:
            if prompt is not None:
                return {"model": "echo-optimizer", "prompt": prompt, "seed": seed}
            return {"model": "echo-optimizer", "messages": messages, "seed": seed}
        from ..llm.client import RequestShape

        shape = RequestShape.for_config(self.config.llm)
        if prompt is not None:
            return shape.document_body(prompt, D=D, seed=seed, grammar=grammar, temperature=temperature, sampling=sampling)
        assert messages is not None
        return shape.body(messages, D=D, seed=seed)

    def count_tokens(self, text: str) -> int:
        """A rough token count: one token per four characters."""
        return len(text) // 4

    def close(self) -> None:
        """Nothing to release."""


@contextmanager
def offline_llm(spread: float = 0.5) -> Iterator[None]:
    """Within the block, every run started by ``ppprops.runner`` talks to an ``EchoOptimizer``."""
    from ..study import use_chat

    with use_chat(lambda config: EchoOptimizer(config, spread=spread)):
        yield
