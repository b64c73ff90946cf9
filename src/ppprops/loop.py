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
    name: str
    proposer: Proposer
    budget: int


def locate(phases: Sequence[Phase], index: int) -> tuple[Phase, int]:
    """The phase and the phase-local iteration that produce candidate ``index``."""
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
    """Replays ``done`` into the proposers, then runs the remaining budget. Returns all candidates."""
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
    is finite, the first candidate."""
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
