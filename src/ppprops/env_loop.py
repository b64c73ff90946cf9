"""The env loop: a study driven on its task's env until nothing is left to ask (``Study.optimize``).

The study schedules trials (``Study.ask`` / ``tell``); this module drives it, as Optuna's
``_optimize.py`` drives its ``Study``: ask a trial (or a round of ``--parallel`` P, one per worker
``run-0`` ... ``run-{P-1}``), evaluate it on the env (the study's ``Evaluator`` or a ``Fleet``),
tell it, call the callbacks, and finalize once the budget is spent or a callback stops the search.
How the loop ended is the run's stored status, so that ``ppprops resume`` knows what to do:

==========================================  ====================================================
the loop ended by                           stored status (and what becomes of the error)
==========================================  ====================================================
the budget spent, or a proposer's stop      ``finished`` (or ``stopped: <reason>``) by ``finalize``
a callback returning False                  ``stopped: stopped by a callback``, then ``finalize``
Ctrl-C                                      ``interrupted`` (resumable); raised
the endpoint down past the retries          ``failed: <error>`` (resumable); raised, naming resume
an env that broke its task's declaration    ``stopped: <error>``; raised as it is
the user's env raised, or the pool died     ``failed: <error>`` (resumable once fixed); raised, naming resume
anything else                               ``failed: <Type>: <first line>``; raised as it is
==========================================  ====================================================

The loop imports nothing of ``study``: it drives any ``DrivenStudy``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, overload

import numpy as np

from .errors import ConfigError, LLMError, StoreError, StudyComplete, TrialsOut, interrupted_by_user
from .evaluation import EpisodeError, EpisodeLimitError, Evaluator, Fleet, PoolError, WorkerError
from .events import RunEvents
from .locks import RUNNING_LOCK, file_lock
from .naming import holders
from .status import RunStatus
from .store import RunStore
from .tasks import FeedbackKeyError
from .values import Candidate, Feedback, FinalEval, Trial

if TYPE_CHECKING:
    from .llm.pacing import Pacer

# Errors of an env that breaks its task's declaration mid-run: the run stops (not resumable as is).
BROKEN_TASK = (FeedbackKeyError, EpisodeLimitError, WorkerError)


class DrivenStudy(Protocol):
    """What the env loop needs of a study (``study.Study`` has it)."""

    run_dir: Path
    store: RunStore

    @property
    def done(self) -> bool:
        """Nothing is left to ask."""
        ...

    @property
    def total(self) -> int:
        """The budget of trials."""
        ...

    @property
    def parallel(self) -> int:
        """P, the trials that may be out at once."""
        ...

    @property
    def out(self) -> list[Trial]:
        """The trials asked for and not yet told."""
        ...

    @property
    def evaluator(self) -> Evaluator:
        """The episode runner of the task's env."""
        ...

    def ask(self, worker: str | None = None, *, wait: bool = True, timeout: float | None = None) -> Trial:
        """The next trial (``Study.ask``)."""
        ...

    @overload
    def tell(self, trial: Trial, *, feedback: Feedback, eval_s: float | None = None) -> Candidate:
        """Tell an evaluated trial (``Study.tell``); returns the recorded candidate."""

    @overload
    def tell(self, trial: Trial, *, failed: str) -> None:
        """Tell that a trial could not be evaluated (``Study.tell``)."""

    def finalize(self, returns: Sequence[float] | None = None, *, events: RunEvents | None = None) -> FinalEval | None:
        """The final evaluation and the policy file (``Study.finalize``)."""
        ...


def optimize(study: DrivenStudy, callbacks: Sequence[Callable[[Candidate, Any], bool | None]], events: RunEvents, *,
             fleet: Fleet | None = None, fail_trials: bool = False, pacer: Pacer | None = None,
             llm_latency: Callable[[], float | None] = lambda: None) -> FinalEval | None:
    """Drive ``study`` on its env to the end (``Study.optimize`` documents the behaviour), holding
    the run's ``RUNNING_LOCK``; returns the final evaluation (None when there is none).

    ``fail_trials``: ``--on-episode-error fail-trial`` (a trial whose env raised is told as failed,
    its error the reason); ``pacer``: the study's request pacer, whose clock this loop restarts;
    ``llm_latency``: seconds the last LLM request took, for the progress events. Raises ConfigError
    when another process runs the study, and the errors of the module docstring's table."""
    try:
        with file_lock(study.run_dir, RUNNING_LOCK, wait=False):
            return _drive(study, callbacks, events, fleet, fail_trials, pacer, llm_latency)
    except BlockingIOError:
        raise ConfigError(f"another process is running {study.run_dir}; wait for it, or stop it first") from None


def _drive(study: DrivenStudy, callbacks: Sequence[Callable[[Candidate, Any], bool | None]], events: RunEvents,
           fleet: Fleet | None, fail_trials: bool, pacer: Pacer | None, llm_latency: Callable[[], float | None]) -> FinalEval | None:
    from .proposers.base import StopSearch

    store = study.store
    evaluator = study.evaluator
    runner: Fleet = fleet if fleet is not None else evaluator
    status, _ = store.run_status()
    if status is not RunStatus.STOPPED:
        store.set_status(RunStatus.RUNNING)
    if pacer is not None:  # this loop's clock starts now: the time since another process's last answer is no evaluation
        pacer.restart()
    done = store.candidates()
    settled = len(done) + store.failed_count()  # a failed trial holds its place in the plan
    events.on_start(settled, study.total if status is not RunStatus.STOPPED else settled)
    best = [max((c.ret for c in done if math.isfinite(c.ret)), default=-np.inf)]
    try:
        while not study.done:
            if study.parallel == 1 and fleet is None and not fail_trials:
                try:
                    trials = [study.ask()]
                except StopSearch:
                    break
            else:
                try:
                    trials = next_round(study)
                except StopSearch:
                    break
            t0 = time.perf_counter()
            if len(trials) == 1 and fleet is None and not fail_trials:
                results: list[Feedback | EpisodeError] = [evaluator.evaluate(trials[0].theta, trials[0].seeds)]
            else:
                results = list(runner.evaluate_each([t.theta for t in trials], [t.seeds for t in trials]))
            eval_s = time.perf_counter() - t0
            stop = False
            for trial, fb in zip(trials, results, strict=True):
                if isinstance(fb, EpisodeError):
                    if not fail_trials:
                        raise fb
                    study.tell(trial, failed=str(fb))
                    events.on_failed(trial.number, str(fb))
                    continue
                cand = study.tell(trial, feedback=fb, eval_s=eval_s)
                if math.isfinite(cand.ret):  # a numerical fault is never the best so far
                    best[0] = max(best[0], cand.ret)
                latency = llm_latency() if cand.source not in ("warmup", "init", "reeval") else None
                events.on_candidate(cand, latency, best[0])
                if any(cb(cand, study) is False for cb in callbacks):
                    stop = True
            if stop:
                store.set_status(RunStatus.STOPPED, "stopped by a callback")
                break
        fe = study.finalize(events=events)
    except KeyboardInterrupt:
        mark(store, RunStatus.INTERRUPTED)
        raise
    except LLMError as e:  # the endpoint stayed down past the retry bound: resumable
        mark(store, RunStatus.FAILED, str(e))
        raise LLMError(saved(str(e), study.run_dir)) from e
    except BROKEN_TASK as e:  # the env broke its declaration
        store.set_status(RunStatus.STOPPED, str(e))
        raise
    except (EpisodeError, PoolError) as e:  # the user's env raised or returned nonsense, or the workers died: fix it, then resume
        mark(store, RunStatus.FAILED, str(e))
        raise type(e)(saved(str(e), study.run_dir)) from None
    except Exception as e:  # nothing above foresaw it: the status says so (not "interrupted"), and the error goes on
        if interrupted_by_user(e):  # a Ctrl-C that Python wrapped (a lazy import it landed in): still a Ctrl-C
            mark(store, RunStatus.INTERRUPTED)
            raise KeyboardInterrupt from e
        mark(store, RunStatus.FAILED, f"{type(e).__name__}: {e}".splitlines()[0])
        raise
    if fe is not None:
        events.on_final(fe)
    return fe


def saved(line: str, run_dir: Path) -> str:
    """``line`` (an error's) with what to do next: the run is kept, and ``resume`` continues it."""
    return f"{line}{_SAVED.format(run_dir=run_dir)}"


def unsaved(line: str, run_dir: Path) -> str:
    """``line`` without what ``saved`` added (the run was not kept after all: ``runner.start``)."""
    return line.removesuffix(_SAVED.format(run_dir=run_dir))


_SAVED = "; the run is saved: continue with 'ppprops resume {run_dir}'"


def next_round(study: DrivenStudy) -> list[Trial]:
    """The trials the loop evaluates next, by number: each of its workers' (``run-0`` ...) held
    trial, or a new one, as many as can be out now. Raises ConfigError when none can be had because
    other workers hold every trial out."""
    got: dict[int, Trial] = {}
    for i in range(study.parallel):
        try:
            t = study.ask(worker=f"run-{i}", wait=False)
        except (TrialsOut, StudyComplete):
            continue
        got.setdefault(t.number, t)
    if not got:
        raise ConfigError(f"every trial out is held by another worker ({holders(study.out)}): tell them (or wait for them), "
                          "then run again")
    return [got[k] for k in sorted(got)]


def mark(store: RunStore, status: RunStatus, reason: str = "") -> None:
    """Best effort: the stored status says how the run ended (a store that fails is left as it is)."""
    try:
        store.set_status(status, reason)
    except (StoreError, KeyboardInterrupt):
        pass
