"""The one search loop: ask a proposer, evaluate, encode, record, tell everyone, report.

A run is a sequence of phases (for PP-ProPS: warm-up, then LLM iterations). Each candidate
index belongs to exactly one (phase, iteration), so a resumed run knows where to continue
from the number of recorded candidates alone.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .client.codec import Codec, encode_feedback
from .proposers.base import Proposer
from .store import RunStore
from .values import Candidate, Feedback

Evaluate = Callable[[np.ndarray, int], tuple[Feedback, Sequence[int]]]
OnCandidate = Callable[[Candidate], None]


@dataclass(frozen=True)
class Phase:
    """A stretch of the run: ``budget`` candidates, each asked of ``proposer`` (warm-up, then the search).

    ``name`` labels it (``warmup``, ``llm``, ``r2po``, ``random``, ``cmaes``); ``budget`` >= 0.
    """

    name: str
    proposer: Proposer
    budget: int


def locate(phases: Sequence[Phase], index: int) -> tuple[Phase, int]:
    """The phase and the phase-local iteration that produce candidate ``index`` (0-based).

    Phases are laid end to end: phase k holds indices [sum of earlier budgets, + its budget).
    Raises IndexError for an index at or past the total budget.
    """
    start = 0
    for ph in phases:
        if index < start + ph.budget:
            return ph, index - start
        start += ph.budget
    raise IndexError(f"candidate {index} is past the run's budget of {start}")


def run_loop(
    phases: Sequence[Phase],
    *,
    evaluate: Evaluate,
    codec: Codec,
    store: RunStore,
    done: Sequence[Candidate] = (),
    on_candidate: OnCandidate | None = None,
) -> list[Candidate]:
    """Replay ``done`` into the proposers, then run the remaining budget. Returns all candidates.

    For each index from ``len(done)`` to the total budget: ask the phase's proposer (``locate``),
    evaluate the raw theta (``evaluate(theta, index)`` -> raw Feedback and the episode seeds),
    encode it (theta~ = A theta, r~ = c r: paper Eq. 5, 7, 8 through ``codec``), record the Candidate in
    ``store``, tell every proposer, then call ``on_candidate``. A proposer's StopSearch and the
    evaluator's errors propagate; the candidates recorded before them stay in the store.
    """
    history = list(done)
    proposers = list(dict.fromkeys(ph.proposer for ph in phases))
    for c in history:
        for p in proposers:
            p.tell(c)
    total = sum(ph.budget for ph in phases)
    for index in range(len(history), total):
        phase, iteration = locate(phases, index)
        t0 = time.perf_counter()
        proposal = phase.proposer.ask(iteration)
        t1 = time.perf_counter()
        feedback, seeds = evaluate(proposal.theta, index)
        t2 = time.perf_counter()
        cand = Candidate(
            index=index,
            iteration=iteration,
            source=proposal.source,
            params=np.asarray(proposal.theta, dtype=np.float64),
            params_enc=codec.encode(proposal.theta),
            feedback=feedback,
            feedback_enc=encode_feedback(codec, feedback),
            clipped=proposal.clipped,
            seeds=tuple(seeds),
            note=proposal.note,
            ask_s=t1 - t0,
            eval_s=t2 - t1,
        )
        store.add_candidate(cand)
        history.append(cand)
        for p in proposers:
            p.tell(cand)
        if on_candidate is not None:
            on_candidate(cand)
    return history


def best_candidate(candidates: Sequence[Candidate]) -> Candidate:
    """Highest finite raw return; the earliest wins a tie (Algorithm 1 updates on strict
    improvement). A NaN or infinite return (a numerical fault) is never the best; if no return
    is finite, the first candidate. Raises ValueError for an empty sequence."""
    if not candidates:
        raise ValueError("no candidates")
    finite = [c for c in candidates if math.isfinite(c.ret)]
    if not finite:
        return candidates[0]
    best = finite[0]
    for c in finite[1:]:
        if c.ret > best.ret:
            best = c
    return best
