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
the endpoint rejects for good always stops the run. Every HTTP try, failed ones included, is
recorded by the recording client it goes through (``llm.recording.RecordingLLM``).

Numerical faults never reach the prompt: a candidate with a non-finite return is left out of
the history (and never becomes the best), non-finite components are dropped and non-finite
diagnostics shown as "non-finite".
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from .. import seeding
from ..client.codec import Codec
from ..llm.protocol import Exchange, LLMRejected, LLMUnavailable
from ..values import Candidate
from ..wire import EncodedEntry, PromptContext, top_k
from ..wire.forms import CHAT, PromptForm
from ..wire.turns import repeats_history
from .base import Bounds, Proposal, SearchProposer, clip_to_box

if TYPE_CHECKING:
    from ..llm.recording import RecordingLLM

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


class StallCounter:
    """LLM-phase candidates in a row that did not raise the best finite encoded return told so far.

    Told every candidate of a run in order (``tell``): a search candidate (source ``llm`` or
    ``fallback``) that raised the best resets ``count`` to 0, one that did not adds 1; every finite
    candidate (warm-up ones too) moves the best. The proposer counts with one, and the audit counts
    the same way from the stored candidates (``stall_count``) to check a document request's
    temperature, so the count is a public function of the shown returns.
    """

    def __init__(self) -> None:
        self.best = -math.inf
        self.count = 0

    def tell(self, candidate: Candidate) -> None:
        """Count ``candidate`` (the next candidate of the run)."""
        fb = candidate.feedback_enc
        finite = math.isfinite(fb.ret) and math.isfinite(candidate.ret)
        if candidate.source in ("llm", "fallback"):
            self.count = 0 if finite and fb.ret > self.best else self.count + 1
        if finite:
            self.best = max(self.best, fb.ret)


def stall_count(candidates: Sequence[Candidate]) -> int:
    """``StallCounter.count`` after telling it ``candidates`` in order."""
    counter = StallCounter()
    for c in candidates:
        counter.tell(c)
    return counter.count


@dataclass(frozen=True)
class LLMSearch:
    """What an LLM proposer takes from its run: the run's recording client ``llm``
    (``llm.recording.RecordingLLM``), the ``codec`` (the only producer of encoded values), the
    public prompt ``context``, ``top_k`` entries shown (0: all, Eq. 9), the raw ``box``, the keyed
    ``streams`` (fallback noise, sampling seeds), ``parse_retries`` corrections before a fallback,
    ``on_llm_failure`` (``stop`` or ``skip`` when the endpoint stays down), ``temperature``
    (``--temperature``; None: each form's own) and ``explore`` (the stall count goes to the form;
    off: 0). Built once per run (``strategies``) and shared by R2PO's two stages."""

    llm: RecordingLLM
    codec: Codec
    context: PromptContext
    top_k: int
    box: Bounds  # the box, or an MLP's layer boxes per coordinate
    streams: seeding.Streams
    parse_retries: int = 2
    on_llm_failure: str = "stop"
    temperature: float | None = None
    explore: bool = True


class LLMProposer(SearchProposer):
    """ProPS (paper Algorithm 1): one LLM call per iteration over the top-K encoded history.

    The prompt is built on the wire side by the prompt ``form`` (``wire.forms``) from the run's
    public context and the encoded entries only; an answer is read by the same form into D encoded
    numbers and decoded (theta = A^-1 theta~) into the box. Every request goes through the run's
    recording client (``LLMSearch.llm``), which records each try as it is sent. An unusable answer
    is corrected (chat form; the document form asks the same document again) up to
    ``parse_retries`` times, then replaced by a fallback: the best policy plus Gaussian noise of
    ``FALLBACK_SIGMA`` x box width in the encoded space (source ``fallback``, with the reason as
    note), drawn from the run's streams. ``on_answer`` sees every answer received (R2PO measures
    its prompts' tokens per character from them).
    """

    def __init__(self, run: LLMSearch, *, form: PromptForm = CHAT, on_answer: Callable[[Exchange], None] | None = None) -> None:
        self.on_answer = on_answer
        self.explore = run.explore
        self.temperature = run.temperature
        self.form = form
        self.llm = run.llm
        self.codec = run.codec
        self.ctx = run.context
        self.k = run.top_k
        self.box = run.box
        self.streams = run.streams
        self.parse_retries = run.parse_retries
        self.on_llm_failure = run.on_llm_failure
        self.nonfinite_skipped = 0
        self.entries: list[EncodedEntry] = []
        self.best: Candidate | None = None
        self.failures: Counter[str] = Counter()
        self._count_lock = threading.Lock()  # a round's requests count their failures from their threads
        self.last_latency: float | None = None
        self.last_exchange: Exchange | None = None
        self.stall = StallCounter()  # LLM-phase candidates in a row that did not raise the best shown return

    @property
    def D(self) -> int:
        """D = (n_s + 1) n_a, the number of parameters."""
        return self.ctx.D

    def tell(self, candidate: Candidate) -> None:
        """Add the candidate's encoded entry to the history (a non-finite return is never shown) and track the best."""
        fb = candidate.feedback_enc
        self.stall.tell(candidate)
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
        return self.form.prompt(self.ctx, self.shown())

    def shown(self) -> list[EncodedEntry]:
        """The history entries the prompt shows (top-K, best last)."""
        return top_k(self.entries, self.k)

    def repeats_history(self, values: tuple[float, ...]) -> bool:
        """True if ``values`` equal an entry of the shown history as the prompt printed it."""
        return repeats_history(self.ctx, values, self.shown())

    rounds = True  # with --parallel P, the P proposals of a round share one shown history (the study waits for the round)

    def latency(self) -> float | None:
        """Seconds of this proposer's latest LLM call (None before the first)."""
        return self.last_latency

    def ask(self, iteration: int) -> Proposal:
        """One LLM proposal (raw theta, shape (D,), clipped into the box), or a fallback after unusable answers.

        Raises LLMRejected when the endpoint refuses for good, and LLMUnavailable past the retries
        when ``on_llm_failure`` is ``stop`` (with ``skip`` a fallback is recorded instead).
        """
        return self._ask(iteration, self.shown(), self.prompt())

    def ask_many(self, iterations: Sequence[int]) -> list[Proposal]:
        """A round: one proposal per iteration, all from the history shown now (the top-K when the
        round starts), as concurrent requests through the one recording client, each with its own
        sampling seed keyed by the secrets (``Codec.sampling_seed`` of its iteration and attempt).
        Proposals come back in the order of ``iterations``; the first error of any request is
        raised once all have ended (every try is recorded either way)."""
        from concurrent.futures import ThreadPoolExecutor

        shown, prompt = self.shown(), self.prompt()
        if len(iterations) <= 1:
            return [self._ask(it, shown, prompt) for it in iterations]
        with ThreadPoolExecutor(max_workers=len(iterations), thread_name_prefix="ppprops-llm") as pool:
            futures = [pool.submit(self._ask, it, shown, prompt) for it in iterations]
            errors = [f.exception() for f in futures]
        first = next((e for e in errors if e is not None), None)
        if first is not None:
            raise first
        return [f.result() for f in futures]

    def _ask(self, iteration: int, shown: list[EncodedEntry], prompt: str) -> Proposal:
        last_error = "no attempt"
        previous: str | None = None
        detail = ""
        for attempt in range(1 + self.parse_retries):
            req = self.form.request(prompt, ctx=self.ctx, shown=shown, iteration=iteration, attempt=attempt, previous=previous,
                                    detail=detail, temperature=self.temperature, stalled=self.stall.count if self.explore else 0)
            seed = self.codec.sampling_seed(self.streams.seed, iteration, attempt)  # keyed: not derivable from the run seed
            try:
                ex = self.llm.send(req, seed=seed)
            except LLMUnavailable as e:
                if self.on_llm_failure != "skip" or isinstance(e, LLMRejected):
                    raise
                with self._count_lock:
                    self.failures["llm_unavailable"] += 1
                return self._fallback(iteration, f"llm_unavailable ({e.kind})")
            if not ex.ok:  # an LLM must raise instead; an HTTP error is never an answer to correct
                raise LLMRejected(f"LLM endpoint refused the request: {ex.error}", (ex,))
            self.last_latency = ex.latency_s
            self.last_exchange = ex
            if self.on_answer is not None:
                self.on_answer(ex)
            result = self.form.judge(ex.content, ex.reasoning, self.ctx, shown, finish_reason=ex.finish_reason)
            if result.error == "length" and ex.context_full:  # the server's context filled up, not the answer budget
                result = replace(result, error="context_full")
            elif result.error == "length" and ex.cut_short:  # cut below the budget, with no sign of a full context
                result = replace(result, error="truncated")
            self.llm.judged(ex, parse_error=result.error, answer_source=result.source if result.ok else "content")
            if result.values is not None:
                with np.errstate(over="ignore"):  # a huge answer decodes to +-inf, then clips to the box
                    theta = self.codec.decode(np.asarray(result.values))
                theta, clipped = clip_to_box(theta, self.box)
                note = "answer taken from the reasoning text" if result.source == "reasoning" else ""
                return Proposal(theta=theta, source="llm", clipped=clipped, note=note)
            kind = result.error or "unknown"
            with self._count_lock:
                self.failures[kind] += 1
            last_error = f"{kind} ({HINTS[kind]})" if kind in HINTS else kind
            previous, detail = ex.content, result.detail
        return self._fallback(iteration, last_error)

    def _fallback(self, iteration: int, reason: str) -> Proposal:
        """The best policy so far plus Gaussian noise drawn in the encoded space the provider sees,
        with a public width (5% of the box width), then decoded and clipped: the shown spread of
        fallbacks is the same whatever the secrets (drawn in raw space, it would state each a_j).
        With no best yet, a warm-up-like draw (the encoded warm-up box when the warm-up is encoded)."""
        lo, hi = self.box
        rng = self.streams.rng(seeding.FALLBACK, iteration)
        if self.best is None:  # every candidate so far had a numerical fault: sample like the warm-up
            if self.ctx.warmup_range is not None:
                wlo, whi = self.ctx.warmup_range
                with np.errstate(over="ignore"):
                    theta = self.codec.decode(rng.uniform(wlo, whi, size=self.D))
                theta, clipped = clip_to_box(theta, self.box)
                return Proposal(theta=theta, source="fallback", clipped=clipped, note=f"after {reason}")
            return Proposal(theta=rng.uniform(lo, hi, size=self.D), source="fallback", note=f"after {reason}")
        noise = rng.normal(0.0, FALLBACK_SIGMA * (hi - lo) * self.codec.public_scale, size=self.D)  # G on the grid, else 1
        with np.errstate(over="ignore"):
            theta = self.codec.decode(self.best.params_enc + noise)
        theta, clipped = clip_to_box(theta, self.box)
        return Proposal(theta=theta, source="fallback", clipped=clipped, note=f"after {reason}")


def _finite_components(components: Mapping[str, float]) -> dict[str, float]:
    return {k: float(v) for k, v in components.items() if math.isfinite(float(v))}


def _finite_diagnostics(diagnostics: Mapping[str, float | str]) -> dict[str, float | str]:
    return {k: (v if isinstance(v, str) or math.isfinite(float(v)) else "non-finite") for k, v in diagnostics.items()}
