"""Hooks a study calls while it runs, for progress displays; the study itself prints nothing."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from .values import Candidate, FinalEval


def _ignore(*args: object) -> None:
    return None


@dataclass(frozen=True)
class RunEvents:
    """Hooks for progress display.

    on_start(done, total): candidates recorded and planned (again when the plan changes: a stop
    rule ended the search); on_candidate(candidate, LLM latency in
    seconds or None, best return so far); on_llm_loading() and on_llm_ready(seconds) around the
    start of the embedded model; on_final_start(episodes) and on_final_episode(done) during the
    final evaluation; on_final(final evaluation) at the end; on_notice(line) for something the user
    should know once (printed even without progress); on_failed(trial number, reason) for a trial
    recorded as failed (it takes its place in the plan, like a candidate).
    """

    on_start: Callable[[int, int], None] = _ignore
    on_candidate: Callable[[Candidate, float | None, float], None] = _ignore
    on_final: Callable[[FinalEval], None] = _ignore
    on_llm_loading: Callable[[], None] = _ignore
    on_llm_ready: Callable[[float], None] = _ignore
    on_final_start: Callable[[int], None] = _ignore
    on_final_episode: Callable[[int], None] = _ignore
    on_notice: Callable[[str], None] = _ignore
    on_failed: Callable[[int, str], None] = _ignore


NO_EVENTS = RunEvents()  # the default: no hook does anything
