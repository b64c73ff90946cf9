"""The ProPS proposer: encoded top-K history -> prompt -> LLM -> parse -> decode -> clip.

It straddles the trust boundary on purpose: it holds the codec (client side) and hands the
wire side only ``EncodedEntry`` values. Parse failures get a bounded number of corrections;
after that the candidate is a documented fallback: the best policy so far plus Gaussian noise
with standard deviation 5% of the box width, clipped to the box, recorded with source
``fallback``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np

from .. import seeding
from ..client.codec import Codec
from ..llm.client import Chat, Exchange
from ..store import Candidate
from ..wire import EncodedEntry, PromptContext, build_correction, build_prompt, parse_answer, top_k
from .base import Proposal, clip_to_box

ExchangeHook = Callable[[int, int, Exchange, str | None], None]
FALLBACK_SIGMA = 0.05  # of the box width


class LLMProposer:
    def __init__(
        self,
        *,
        chat: Chat,
        codec: Codec,
        context: PromptContext,
        top_k: int,
        box: tuple[float, float],
        seed: int,
        parse_retries: int = 2,
        on_exchange: ExchangeHook | None = None,
    ) -> None:
        self.chat = chat
        self.codec = codec
        self.ctx = context
        self.k = top_k
        self.box = box
        self.seed = seed
        self.parse_retries = parse_retries
        self.on_exchange = on_exchange
        self.entries: list[EncodedEntry] = []
        self.best: Candidate | None = None
        self.failures: Counter[str] = Counter()
        self.last_latency: float | None = None

    @property
    def D(self) -> int:
        return self.ctx.D

    def tell(self, candidate: Candidate) -> None:
        fb = candidate.feedback_enc
        detailed = self.ctx.detailed_feedback
        self.entries.append(
            self.codec.entry(
                candidate.index,
                candidate.params_enc,
                fb.ret,
                fb.components if detailed else {},
                fb.diagnostics if detailed else {},
            )
        )
        if self.best is None or candidate.ret > self.best.ret:
            self.best = candidate

    def prompt(self) -> str:
        return build_prompt(self.ctx, top_k(self.entries, self.k))

    def ask(self, iteration: int) -> Proposal:
        messages = [{"role": "user", "content": self.prompt()}]
        last_error = "no attempt"
        for attempt in range(1 + self.parse_retries):
            ex = self.chat.complete(messages, D=self.D, seed=seeding.llm_seed(self.seed, iteration, attempt))
            self.last_latency = ex.latency_s
            result = parse_answer(ex.content, self.D) if ex.ok else None
            error = (result.error if result is not None else "http_error")
            if self.on_exchange is not None:
                self.on_exchange(iteration, attempt, ex, error)
            if result is not None and result.values is not None:
                theta = self.codec.decode(np.asarray(result.values))
                theta, clipped = clip_to_box(theta, self.box)
                return Proposal(theta=theta, source="llm", clipped=clipped)
            self.failures[error or "unknown"] += 1
            last_error = error or "unknown"
            detail = result.detail if result is not None else (ex.error or "the request failed")
            messages = [
                messages[0],
                {"role": "assistant", "content": ex.content or "(empty)"},
                {"role": "user", "content": build_correction(detail, self.D)},
            ]
        return self._fallback(iteration, last_error)

    def _fallback(self, iteration: int, reason: str) -> Proposal:
        if self.best is None:
            raise RuntimeError("LLMProposer needs at least one evaluated candidate (the warm-up) before asking")
        lo, hi = self.box
        noise = seeding.rng(self.seed, seeding.FALLBACK, iteration).normal(0.0, FALLBACK_SIGMA * (hi - lo), size=self.D)
        theta, clipped = clip_to_box(self.best.params + noise, self.box)
        return Proposal(theta=theta, source="fallback", clipped=clipped, note=f"after {reason}")
