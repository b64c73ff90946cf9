"""An offline stand-in for the LLM, so audits and attacks can be exercised on many runs quickly.

``EchoOptimizer`` is an ``llm.protocol.LLM`` that answers each request the way a simple optimizer
in the encoded space would: it reads the best history entry (last in the prompt, as the request's
form prints it) and perturbs it with Gaussian noise scaled to each coordinate's magnitude. It sees
exactly what a provider sees, so its transcripts have the structure of real ones (warm-up first,
LLM answers that may leave the box and get clipped), and it records the body the run's own client
would have sent, so the audit reads a real one. Pass it as a study's model: ``llm=EchoOptimizer(config.llm)``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection

import numpy as np

from ..llm.client import RequestShape
from ..llm.protocol import Exchange
from ..llm.settings import LLMConfig
from ..wire.forms import ENDPOINT_CHAT, ENDPOINT_COMPLETIONS, FORMS, FormRequest
from ..wire.transcript import ShownEntry

MODEL_NAME = "echo-optimizer"  # the model its bodies name when it is given no endpoint settings


class EchoOptimizer:
    """An ``LLM`` (both prompt forms): best shown entry + N(0, spread * (|x| + 1)) per coordinate, two decimals.

    ``llm`` is the endpoint the recorded bodies are written for (None: the embedded model's
    fields under the model name ``echo-optimizer``); ``calls`` counts the requests answered.
    """

    endpoints: Collection[str] = (ENDPOINT_CHAT, ENDPOINT_COMPLETIONS)

    def __init__(self, llm: LLMConfig | None = None, *, spread: float = 0.5) -> None:
        self.spread = spread
        self.calls = 0
        self.shape = RequestShape.for_config(llm) if llm is not None else RequestShape(LLMConfig(), model=MODEL_NAME, grammar_ok=True)

    def send(self, request: FormRequest, *, seed: int | None = None, before_try: Callable[[str, int], None] | None = None,
             after_failure: Callable[[Exchange], None] | None = None) -> Exchange:
        """Answer ``request``: ``{"params": [...]}`` for a chat request, the continuation of the open
        list for a document; from the history entries of the prompt (zeros plus noise when it shows
        none of length D). ``seed`` fixes the noise. Latency 0. ``before_try`` sees the body first
        (``llm.recording``); it never fails, so ``after_failure`` is never called."""
        self.calls += 1
        body = json.dumps(self.shape.body(request, seed))
        if before_try is not None:
            before_try(body, 0)
        form = FORMS[request.form]
        prompt = request.prompt if request.endpoint == ENDPOINT_COMPLETIONS else (request.messages or ({"content": ""},))[0]["content"]
        proposal = self._propose(form.entries(prompt or ""), request.D, seed)
        if request.endpoint == ENDPOINT_COMPLETIONS:
            content = ",".join(f"{i}:{v:.2f}" for i, v in enumerate(proposal)) + "]"
        else:
            content = json.dumps({"params": [round(float(v), 2) for v in proposal]})
        finish = "stop" if request.endpoint == ENDPOINT_COMPLETIONS else None
        return Exchange.answer(request, content, body=body, finish_reason=finish)

    def _propose(self, entries: list[ShownEntry], D: int, seed: int | None) -> np.ndarray:
        rng = np.random.default_rng(seed)
        if entries and len(entries[-1].params) == D:
            best = np.array([float(t) for t in entries[-1].params])
        else:
            best = np.zeros(D)
        return best + rng.normal(0.0, self.spread * (np.abs(best) + 1.0))

    def close(self) -> None:
        """Nothing to release."""
