"""The ProPS proposer: encoded top-K history -> prompt -> LLM -> parse -> decode -> clip.

It straddles the trust boundary on purpose: it holds the codec (client side) and hands the
wire side only ``EncodedEntry`` values. Where the proposal comes from is ``wire.parse``'s rule
(the requested answer object in the final content; reasoning only when the content is empty and
the reasoning holds an explicit final answer, recorded ``answer_source = reasoning``; never an
answer cut off at the token limit). A proposal equal to an entry of the history just shown, at
the precision the prompt printed it, is not a new proposal: it is counted (``repeats_history``)
and asked again. Unusable answers get a bounded number of corrections; after that the candidate
is a documented fallback: the best policy so far plus Gaussian noise with standard deviation 5%
of the box width, clipped to the box, recorded with source ``fallback``.

Two prompt forms (``form``): ``chat``, the paper's instruction prompt as one chat message, and
``document``, the history as a document for a base model to continue (``wire.document``), sent
to the completions endpoint with a grammar fitted to the shown history. A document answer is
``[`` plus the continuation up to its first ``]`` (``wire.parse.read_continuation``); an
unusable one is asked again with the same document and the next seed (there is no conversation
to correct). Everything else (repeats, fallbacks, recording) is the same in both forms.

A correction repeats the model's final text (never its reasoning or markup) and says what was
wrong (``wire.turns.correction_messages``, which the audit rebuilds too); an HTTP error never reaches the model (the client adapts, retries or raises). An
endpoint that stays down past the client's retry bound either stops the run (``stop``,
resumable) or, with ``skip``, yields a fallback candidate noted ``llm_unavailable``; a request
the endpoint rejects for good always stops the run. Every HTTP try, failed ones included, goes
to ``on_exchange``.

Numerical faults never reach the prompt: a candidate with a non-finite return is left out of
the history (and never becomes the best), non-finite components are dropped and non-finite
diagnostics shown as "non-finite".
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np

from .. import seeding
from ..client.codec import Codec
from ..llm.client import Chat, Exchange, LLMRejected, LLMUnavailable
from ..values import Candidate
from ..wire import EncodedEntry, ParseResult, PromptContext, build_prompt, top_k
from ..wire.document import build_document, continuation_grammar, document_temperature
from ..wire.turns import correction_messages, judge_answer, judge_continuation, prompt_messages, repeats_history
from .base import Proposal, clip_to_box

ExchangeHook = Callable[[int, int, Exchange, str | None], None]
FALLBACK_SIGMA = 0.05  # of the box width
# What the user can do about an answer failure, in the fallback note ("after KIND (HINT)").
HINTS = {
    "length": "answers were cut off at the token limit: raise --max-tokens or lower --reasoning-effort",
    "reasoning_only": "answers held only reasoning: raise --max-tokens or lower --reasoning-effort",
    "context_full": "the server's context is full (prompt and answer filled it; --max-tokens cannot help): start the "
                    "server with a larger context (llama.cpp -c/--ctx-size, Ollama num_ctx; the embedded model: "
                    "--context-size) or send a smaller prompt (--top-k, --param-digits)",
    "repeats_history": "answers repeated policies from the history",
}


class LLMProposer:
    """ProPS (paper Algorithm 1): one LLM call per iteration over the top-K encoded history.

    The prompt is built on the wire side from ``context`` and the encoded entries only; an answer is
    parsed into D encoded numbers and decoded (theta = A^-1 theta~) into the box. An unusable answer
    is corrected (chat form; the document form asks the same document again with the next seed) up to
    ``parse_retries`` times, then replaced by a fallback: the best policy plus Gaussian noise of
    ``FALLBACK_SIGMA`` x box width (source ``fallback``, with the reason as note).
    """

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
        on_llm_failure: str = "stop",
        form: str = "chat",
        temperature: float | None = None,
    ) -> None:
        """``form`` ``chat`` sends the paper's instruction prompt as a chat message; ``document``
        sends the history as a document to continue (``wire.document``) to the completions
        endpoint, constrained by ``continuation_grammar``, at ``document_temperature`` (``temperature``
        is ``--temperature``; None alternates the form's defaults)."""
        self.temperature = temperature
        if form not in ("chat", "document"):
            raise ValueError(f"unknown prompt form {form!r} (known: chat, document)")
        self.form = form
        self.chat = chat
        self.codec = codec
        self.ctx = context
        self.k = top_k
        self.box = box
        self.seed = seed
        self.parse_retries = parse_retries
        self.on_exchange = on_exchange
        self.on_llm_failure = on_llm_failure
        self.nonfinite_skipped = 0
        self.entries: list[EncodedEntry] = []
        self.best: Candidate | None = None
        self.failures: Counter[str] = Counter()
        self.last_latency: float | None = None

    @property
    def D(self) -> int:
        """D = (n_s + 1) n_a, the number of parameters."""
        return self.ctx.D

    def tell(self, candidate: Candidate) -> None:
        """Add the candidate's encoded entry to the history (a non-finite return is never shown) and track the best."""
        fb = candidate.feedback_enc
        if not (math.isfinite(fb.ret) and math.isfinite(candidate.ret)):
            self.nonfinite_skipped += 1  # a numerical fault: never shown, never the best
            return
        detailed = self.ctx.detailed_feedback
        self.entries.append(
            self.codec.entry(
                candidate.index,
                candidate.params_enc,
                fb.ret,
                _finite_components(fb.components) if detailed else {},
                _finite_diagnostics(fb.diagnostics) if detailed else {},
            )
        )
        if self.best is None or candidate.ret > self.best.ret:
            self.best = candidate

    def prompt(self) -> str:
        """The prompt of the next ask: the public context and the top-K history (best last), in the run's form."""
        if self.form == "document":
            return build_document(self.ctx, self.shown())
        return build_prompt(self.ctx, self.shown())

    def grammar(self) -> str:
        """The continuation grammar of the document form, shaped by the shown history."""
        return continuation_grammar(self.D, self.shown(), self.ctx)

    def shown(self) -> list[EncodedEntry]:
        """The history entries the prompt shows (top-K, best last)."""
        return top_k(self.entries, self.k)

    def repeats_history(self, values: tuple[float, ...]) -> bool:
        """True if ``values`` equal an entry of the shown history as the prompt printed it."""
        return repeats_history(self.ctx, values, self.shown())

    def ask(self, iteration: int) -> Proposal:
        """One LLM proposal (raw theta, shape (D,), clipped into the box), or a fallback after unusable answers.

        Raises LLMRejected when the endpoint refuses for good, and LLMUnavailable past the retries
        when ``on_llm_failure`` is ``stop`` (with ``skip`` a fallback is recorded instead).
        """
        prompt = self.prompt()
        messages = prompt_messages(prompt)
        grammar = self.grammar() if self.form == "document" else None
        last_error = "no attempt"
        for attempt in range(1 + self.parse_retries):
            seed = self.codec.sampling_seed(self.seed, iteration, attempt)  # keyed: not derivable from the run seed
            try:
                if self.form == "document":  # a retry asks the same document again, with the next seed
                    ex = self.chat.complete_document(prompt, D=self.D, seed=seed, grammar=grammar,
                                                     temperature=document_temperature(iteration, attempt, self.temperature))
                else:
                    ex = self.chat.complete(messages, D=self.D, seed=seed)
            except LLMUnavailable as e:
                self._record(iteration, attempt, e.failures)
                if self.on_llm_failure != "skip" or isinstance(e, LLMRejected):
                    raise
                self.failures["llm_unavailable"] += 1
                return self._fallback(iteration, f"llm_unavailable ({e.kind})")
            self._record(iteration, attempt, ex.failures)
            if not ex.ok:  # a Chat must raise instead; an HTTP error is never an answer to correct
                self._record(iteration, attempt, (ex,))
                raise LLMRejected(f"LLM endpoint refused the request: {ex.error}", (ex,))
            self.last_latency = ex.latency_s
            result = self._read(ex)
            ex = replace(ex, answer_source=result.source if result.ok else "content")
            if self.on_exchange is not None:
                self.on_exchange(iteration, attempt, ex, result.error)
            if result.values is not None:
                with np.errstate(over="ignore"):  # a huge answer decodes to +-inf, then clips to the box
                    theta = self.codec.decode(np.asarray(result.values))
                theta, clipped = clip_to_box(theta, self.box)
                note = "answer taken from the reasoning text" if result.source == "reasoning" else ""
                return Proposal(theta=theta, source="llm", clipped=clipped, note=note)
            kind = result.error or "unknown"
            self.failures[kind] += 1
            last_error = f"{kind} ({HINTS[kind]})" if kind in HINTS else kind
            if self.form == "chat":
                messages = correction_messages(prompt, ex.content, result.detail, self.D)
        return self._fallback(iteration, last_error)

    def _read(self, ex: Exchange) -> ParseResult:
        """The proposal in an answer (``wire.turns.judge_answer``; a document continuation:
        ``judge_continuation``), refused if it repeats the history shown."""
        if self.form == "document":
            result = judge_continuation(ex.content, self.ctx, self.shown(), finish_reason=ex.finish_reason)
        else:
            result = judge_answer(ex.content, ex.reasoning, self.ctx, self.shown(), finish_reason=ex.finish_reason)
        return replace(result, error="context_full") if result.error == "length" and ex.context_full else result

    def _record(self, iteration: int, attempt: int, tries: tuple[Exchange, ...]) -> None:
        if self.on_exchange is not None:
            for t in tries:
                self.on_exchange(iteration, attempt, t, None)

    def _fallback(self, iteration: int, reason: str) -> Proposal:
        """The best policy so far plus Gaussian noise drawn in the encoded space the provider sees,
        with a public width (5% of the box width), then decoded and clipped: the shown spread of
        fallbacks is the same whatever the secrets (drawn in raw space, it would state each a_j).
        With no best yet, a warm-up-like draw (the encoded warm-up box when the warm-up is encoded)."""
        lo, hi = self.box
        rng = seeding.rng(self.seed, seeding.FALLBACK, iteration)
        if self.best is None:  # every candidate so far had a numerical fault: sample like the warm-up
            if self.ctx.warmup_range is not None:
                wlo, whi = self.ctx.warmup_range
                with np.errstate(over="ignore"):
                    theta = self.codec.decode(rng.uniform(wlo, whi, size=self.D))
                theta, clipped = clip_to_box(theta, self.box)
                return Proposal(theta=theta, source="fallback", clipped=clipped, note=f"after {reason}")
            return Proposal(theta=rng.uniform(lo, hi, size=self.D), source="fallback", note=f"after {reason}")
        noise = rng.normal(0.0, FALLBACK_SIGMA * (hi - lo), size=self.D)
        with np.errstate(over="ignore"):
            theta = self.codec.decode(self.best.params_enc + noise)
        theta, clipped = clip_to_box(theta, self.box)
        return Proposal(theta=theta, source="fallback", clipped=clipped, note=f"after {reason}")


def _finite_components(components: Mapping[str, float]) -> dict[str, float]:
    return {k: float(v) for k, v in components.items() if math.isfinite(float(v))}


def _finite_diagnostics(diagnostics: Mapping[str, float | str]) -> dict[str, float | str]:
    return {k: (v if isinstance(v, str) or math.isfinite(float(v)) else "non-finite") for k, v in diagnostics.items()}
