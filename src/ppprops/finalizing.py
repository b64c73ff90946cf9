"""Finalizing a study: which trial is handed over, its final evaluation, and the policy file
(``Study.finalize``).

The trial handed over is ``loop.select_best``'s: after the selection stage, the best mean over all
its episodes; before it, the best search-time return. Its final evaluation is the user's own
returns when given (episodes of ``Study.policy()`` run on the robot), else, for a task with an env,
``final_episodes`` episodes on fresh seeds (``seeding.final_eval_seeds``: never used in the search);
one already stored for the same trial is kept, so a finalize that is resumed does not run them
twice. The policy file (``best_policy.json``, ``policy_file``) is written whole or not at all.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ConfigError, StoreError
from .fileio import write_json_atomic
from .loop import pooled_returns, search_candidates, select_best
from .rundir import POLICY_NAME, final_returns, policy_path
from .seeding import final_eval_seeds
from .status import RunStatus
from .store import RunStore
from .values import Candidate, FinalEval

if TYPE_CHECKING:
    from .evaluation import Evaluator
    from .events import RunEvents


def all_failed(store: RunStore, run_dir: Path) -> str:
    """The one line for a search whose every trial failed: nothing to re-evaluate or hand over."""
    failed = store.failed_trials()
    first = f"; the first, trial {failed[0][0].number}: {failed[0][1]}" if failed else ""
    return (f"every search trial failed ({len(failed)} of {store.next_number()}{first}): there is no candidate to "
            f"re-evaluate or hand over; 'ppprops show {run_dir}' lists each reason, and once the evaluation is "
            f"fixed 'ppprops study retry {run_dir} TRIAL' asks a failed trial again")


def final_evaluation(store: RunStore, run_dir: Path, returns: Sequence[float] | None,
                     run_episodes: Callable[[Candidate], FinalEval] | None) -> tuple[Candidate, FinalEval | None]:
    """The trial to hand over and its final evaluation, stored (module docstring).

    ``returns``: the user's own final episode returns (raw reward units), or None; ``run_episodes``:
    runs the final episodes of a trial on the task's env (None for a task without one). Raises
    ConfigError while a trial is pending (unless the search stopped on purpose), before any trial
    is told (or when every one failed), or for returns that are not one or more finite numbers."""
    pending = store.pending_trial()
    if pending is not None and store.run_status()[0] is not RunStatus.STOPPED:
        raise ConfigError(f"trial {pending.number} is pending: tell it before finalizing")
    done = store.candidates()
    if not search_candidates(done):
        raise ConfigError(all_failed(store, run_dir) if store.failed_count() else "no trial has been told: nothing to finalize")
    best = select_best(done)
    fe = store.final_eval()
    if returns is not None:
        values = tuple(float(r) for r in returns)
        if not values or not all(math.isfinite(r) for r in values):
            raise ConfigError("final returns must be one or more finite numbers")
        fe = FinalEval(candidate_index=best.index, returns=values, seeds=())
        store.set_final_eval(fe)
    elif run_episodes is not None and (fe is None or fe.candidate_index != best.index):
        fe = run_episodes(best)
        store.set_final_eval(fe)
    return best, fe


def env_final_episodes(evaluator: Callable[[], Evaluator], *, seed: int, episodes: int,
                       events: RunEvents) -> Callable[[Candidate], FinalEval]:  # fmt: skip
    """The final evaluation of a trial on the task's env (``evaluator()``, made when first needed):
    ``episodes`` episodes on the fresh seeds of run seed ``seed`` (``seeding.final_eval_seeds``),
    reported to ``events`` as they come."""

    def run(best: Candidate) -> FinalEval:
        seeds = final_eval_seeds(seed, episodes)
        return FinalEval(candidate_index=best.index, returns=final_returns(evaluator(), best.params, seeds, events), seeds=tuple(seeds))

    return run


def finish_status(store: RunStore) -> None:
    """The study's status once finalized: ``finished``, or ``stopped: <reason>`` as it was when
    the search stopped on purpose or a stop rule ended it early (``stopping.stop_reason``)."""
    from .stopping import stop_reason

    status, reason = store.run_status()
    early = stop_reason(store)
    if status is RunStatus.STOPPED or early:
        store.set_status(RunStatus.STOPPED, reason if status is RunStatus.STOPPED else str(early))
    else:
        store.set_status(RunStatus.FINISHED)


def provenance(store: RunStore, best: Candidate, fe: FinalEval | None, *, method: str, seed: int) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The policy file's ``search`` record (run id, method, run seed, the trial's search-time
    return and number, and the selection stage's mean over its episodes when it ran) and its
    ``final_eval`` record (mean, std, episodes, run seed; None without a final evaluation)."""
    final = {"mean": fe.mean, "std": fe.std, "episodes": len(fe.returns), "seed": seed} if fe is not None and fe.returns else None
    search: dict[str, Any] = {"run_id": store.run_id(), "method": method, "seed": seed, "return": best.ret, "candidate": best.index}
    pooled = pooled_returns(store.candidates()).get(best.index)
    if pooled:
        search["selection"] = {"mean": float(np.mean(pooled)), "episodes": len(pooled)}
    return search, final


def write_policy(run_dir: Path, document: dict[str, Any]) -> None:
    """Write the policy file of ``run_dir`` atomically (a stale temporary file of a run killed
    mid-write is removed first). Raises StoreError, naming resume, when it cannot be written."""
    path = policy_path(run_dir)
    for stale in run_dir.glob(f".{POLICY_NAME}.*.tmp"):  # left by a run killed mid-write
        stale.unlink(missing_ok=True)
    try:
        write_json_atomic(path, document)
    except OSError as e:
        raise StoreError(f"cannot write {path}: {e.strerror or e}; then continue with 'ppprops resume {run_dir}'") from None
