"""Which trials a study can hand out now: the one a worker holds already, why nothing more can be
asked (the budget is spent, the study stopped or is finalized), and which iterations of a phase can
be asked while others are out (``--parallel`` P, the rounds of the LLM phase, CMA-ES's generations).

Functions of what the store holds and the phase's proposer; ``Study.ask`` calls them under the
study's lock and makes the trials (``new_trials``); ``Study.retry`` asks a failed trial again
(``check_retry``).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ConfigError, StudyComplete, TrialsOut
from .finalizing import all_failed
from .loop import locate
from .naming import holder, holders
from .phases import RunPhases
from .status import RunStatus
from .store import RunStore
from .tasks import Task
from .values import Trial

if TYPE_CHECKING:
    from .proposers.base import Phase, Proposal


def held(out: Sequence[Trial], worker: str, parallel: int) -> tuple[Trial, bool] | None:
    """The trial out that ``worker`` gets again, and whether it must be handed to it first (True: no
    worker holds it yet: the rest of a round, or a failed trial asked again); None: none.

    ``worker`` "" is the unnamed worker; at P = 1 it gets the one pending trial whoever holds it
    (as before workers had names).
    """
    mine = [t for t in out if t.worker == worker]
    if mine:
        return mine[0], False
    free = [t for t in out if t.worker is None]
    if free:
        return free[0], True
    if parallel == 1 and out and not worker:
        return out[0], False
    return None


def wait_for(ask_once: Callable[[], Trial | str], *, wait: bool, timeout: float | None, out: Callable[[], int]) -> Trial:
    """The first trial ``ask_once`` gives (it returns a trial or why it must wait), asked again
    after waits of 0.02 s doubling up to 0.5 s, for up to ``timeout`` seconds (None: no limit).
    Raises TrialsOut, with the last reason and ``out()`` trials out, past the timeout or at once
    when ``wait`` is False."""
    deadline = None if timeout is None else time.monotonic() + timeout
    delay = 0.02
    while True:
        got = ask_once()
        if isinstance(got, Trial):
            return got
        if not wait or (deadline is not None and time.monotonic() >= deadline):
            raise TrialsOut(got, out=out())
        time.sleep(delay)
        delay = min(delay * 2, 0.5)


def finalized(store: RunStore, run_dir: Path) -> bool:
    """True once the study's policy is handed over: status finished, or stopped (on purpose) with a
    final evaluation or its policy file written."""
    from .rundir import POLICY_NAME

    status, _ = store.run_status()
    return status is RunStatus.FINISHED or (status is RunStatus.STOPPED and (store.final_eval() is not None or
                                                                           (Path(run_dir) / POLICY_NAME).exists()))


def check_left(store: RunStore, run_dir: Path, total: int, out: Sequence[Trial]) -> None:
    """Raise StudyComplete, with why, when nothing more can be asked: the study is finalized (its
    status finished, or stopped with its policy handed over), it stopped, or all ``total`` trials
    of its budget are asked (``out`` the trials still out)."""
    status, reason = store.run_status()
    if finalized(store, run_dir):
        raise StudyComplete(f"study {run_dir} is finalized ({store.candidate_count()} of {total} trials told): nothing more to ask",
                            finalized=True)
    if status is not RunStatus.STOPPED and store.next_number() < total:
        return
    from .stopping import stop_reason

    told, failed = store.candidate_count(), store.failed_count()
    if not (status is RunStatus.STOPPED and reason):
        reason = "" if out else stop_reason(store) or ""  # a stop rule ended the search early
    why = (f"it stopped: {reason}" if reason
           else f"all {total} trials are told" if not out and not failed
           else f"all {total} trials are settled: {told} told, {failed} failed (ppprops study retry "
                f"{run_dir} TRIAL asks a failed one again)" if not out
           else f"every trial is asked; {holders(out)} still out")  # fmt: skip
    raise StudyComplete(f"study {run_dir} has nothing more to ask ({why}); finalize it" + (" once they are told" if out else ""))


def check_retry(store: RunStore, number: int, run_dir: Path, parallel: int) -> None:
    """Refuse to ask trial ``number`` again unless it failed, the study is not finalized (its
    policy is handed over) and fewer than P trials are out: ConfigError, one line."""
    if finalized(store, run_dir):
        raise ConfigError(f"study {run_dir} is finalized (its best policy is handed over): a failed trial can be "
                          "retried only before 'ppprops study finalize'")
    out = store.pending_trials()
    if number not in {t.number for t, _ in store.failed_trials()}:
        holding = next((t for t in out if t.number == number), None)
        state = ("it was told" if store.trial_state(number) == "told"
                 else f"it is out, held by {holder(holding)}" if holding is not None
                 else "it was never asked")  # fmt: skip
        raise ConfigError(f"trial {number} did not fail ({state}): only a failed trial can be retried")
    if len(out) >= parallel:
        raise ConfigError(f"{len(out)} trials are out, the most at once (--parallel {parallel}): tell one before retrying trial {number}")


def wait_for_earlier(phase: Phase, first: int, out: Sequence[Trial]) -> str | None:
    """Why ``phase`` (whose first trial is number ``first``) cannot start yet: trials of an earlier
    phase are out (one line); None: it can."""
    earlier = [t for t in out if t.number < first]
    if earlier:
        return f"the {phase.name} phase starts when the {earlier[0].phase} phase is told: {holders(earlier)} still out"
    return None


def askable(phase: Phase, iteration: int, out: Sequence[Trial], parallel: int) -> list[int] | str:
    """The iterations of ``phase`` to ask now, from ``iteration`` (its next), with ``out`` the trials
    out: up to P - len(out), within the phase's budget, within one round for a proposer that asks in
    rounds (``SearchProposer.rounds``: none while the last round is out), and only those the
    proposer is ready for (``SearchProposer.ready``). Or why none can be asked (one line)."""
    proposer = phase.proposer
    end = phase.offset + phase.budget
    if parallel > 1 and proposer.rounds:  # one shown history per round of P
        if out:
            return f"the next round of {parallel} starts when the last one is told: {holders(out)} still out"
        end = min(end, (iteration // parallel) * parallel + parallel)
    iterations = list(itertools.takewhile(proposer.ready, range(iteration, min(end, iteration + parallel - len(out)))))
    if not iterations:
        return f"the {phase.name} phase waits for its trials that are out: {holders(out)}"
    return iterations


def propose(phases: RunPhases, store: RunStore, run_dir: Path, out: Sequence[Trial], *, worker: str, parallel: int, task: Task,
            episode_seeds: Callable[[int], tuple[int, ...]], queue: list[dict[str, Any]] | None = None) -> list[Trial] | str:  # fmt: skip
    """The next trials to hand out (the first to ``worker``), proposed by the phase the store's next
    trial number falls in, with ``out`` the trials out (fewer than P); or why none can be asked yet
    (one line: ``wait_for_earlier``, ``askable``). The proposers are told every settled trial first.
    Queued given policies (``queue``, ``warm_start.take_queued``: removed from it) come first, alone.

    Raises ConfigError when the selection stage is reached and every search trial failed, and the
    proposer's StopSearch after storing the study's status ``stopped: <reason>``.
    """
    from .proposers.base import StopSearch

    phases.sync()
    n = store.next_number()
    phase, iteration = locate(phases.phases(), n)
    wait = wait_for_earlier(phase, n - (iteration - phase.offset), out)
    if wait is not None:
        return wait
    if phase.name == "selection" and store.candidate_count() == 0:
        raise ConfigError(all_failed(store, run_dir))
    iterations = askable(phase, iteration, out, parallel)
    if isinstance(iterations, str):
        return iterations
    t0 = time.perf_counter()
    if queue:
        from .warm_start import take_queued

        given = take_queued(queue, phase.name, iterations)
        if given:
            return new_trials(phase, iterations[:len(given)], given, first=n, worker=worker, ask_s=time.perf_counter() - t0, task=task,
                              episode_seeds=episode_seeds)  # fmt: skip
    try:
        proposals = phase.proposer.ask_many(iterations)
    except StopSearch as stop:
        store.set_status(RunStatus.STOPPED, stop.reason)
        raise
    return new_trials(phase, iterations, proposals, first=n, worker=worker, ask_s=time.perf_counter() - t0, task=task,
                      episode_seeds=episode_seeds)


def new_trials(phase: Phase, iterations: Sequence[int], proposals: Sequence[Proposal], *, first: int, worker: str, ask_s: float,
               task: Task, episode_seeds: Callable[[int], tuple[int, ...]]) -> list[Trial]:  # fmt: skip
    """The trials of ``proposals`` (one per iteration of ``phase``), numbered from ``first``; the
    first handed to ``worker``, the rest to whoever asks next. A proposal's own seeds are kept, else
    trial n's are ``episode_seeds(n)``; ``ask_s`` is the seconds the proposals took."""
    return [Trial(number=first + k, phase=phase.name, iteration=it, source=p.source, theta=np.asarray(p.theta, dtype=np.float64),
                  n_s=task.n_s, n_a=task.n_a, seeds=p.seeds if p.seeds is not None else episode_seeds(first + k),
                  clipped=p.clipped, note=p.note, ask_s=ask_s, reevaluates=p.reevaluates, worker=worker if k == 0 else None,
                  policy=None if task.policy.is_linear else task.policy)
            for k, (it, p) in enumerate(zip(iterations, proposals, strict=True))]  # fmt: skip
