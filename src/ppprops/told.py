"""The told-feedback check: what a robot tells about a trial, checked against the task and made one
``Feedback`` (``Study.tell``, as Optuna keeps ``_tell.py`` beside its study).

A tell gives raw values: one episode's return or one per episode (reward units), and per episode
the declared reward components (each one's sum over the episode, by name) and diagnostics (each
one's value at the end, or a text). The candidate's feedback is their mean over the episodes
(paper Sec. II-C). Before the values, the tell itself: the trial must be pending, held by the
worker that tells it, with the parameters the study asked for (``not_pending``, ``check_teller``).
Everything here is a function of the told values, the trial and the task's facts (its name, its
declared components and diagnostics); every refusal is one ``ConfigError`` line, raised before
anything is stored.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ConfigError
from .evaluation import Episode, aggregate
from .status import RunStatus
from .values import Candidate, Feedback, Trial

if TYPE_CHECKING:
    from .client.codec import Codec
    from .store import RunStore
    from .tasks import Task


def not_pending(store: RunStore, number: int, out: Sequence[Trial], *, run_dir: Path, total: int) -> ConfigError:
    """The one line that says why trial ``number`` cannot be told: it is not among ``out`` (the
    trials pending in ``store``, a study of ``total`` trials in ``run_dir``). It does not exist, was
    told, failed, the study is finalized or has nothing more to ask, it was never asked, or the
    study waits for other trials."""
    recorded = store.candidate_count()
    if number < 0:
        return ConfigError(f"trial {number} does not exist: trials are numbered from 0 (ask gives the next one)")
    if store.trial_state(number) == "told":
        return ConfigError(f"trial {number} was already told; each trial is told once")
    failed = dict((t.number, why) for t, why in store.failed_trials())
    if number in failed:
        return ConfigError(f"trial {number} failed ({failed[number]}); ask it again with 'ppprops study retry {run_dir} "
                           f"{number}' (study.retry) first")
    if not out:
        status, _ = store.run_status()
        if status is RunStatus.FINISHED:
            return ConfigError(f"study {run_dir} is finalized ({recorded} of {total} trials told): nothing more can be told")
        if status is RunStatus.STOPPED or store.next_number() >= total:
            return ConfigError(f"no trial is pending and study {run_dir} has nothing more to ask ({recorded} of "
                               f"{total} trials told): finalize it")
    if number >= store.next_number():
        return ConfigError(f"trial {number} has not been asked yet: ask hands out the next trial ({store.next_number()})")
    if len(out) > 1:
        return ConfigError(f"trial {number} is not pending (the study waits for trials {', '.join(str(t.number) for t in out)})")
    waiting = "no trial is pending: ask first" if not out else f"the study waits for trial {out[0].number}"
    return ConfigError(f"trial {number} is not the study's pending trial ({waiting})")


def check_teller(pending: Trial, teller: str | None, theta: Any, *, run_dir: Path) -> None:
    """Refuse a tell of ``pending`` by another than the worker holding it (``teller``; None: the
    unnamed worker), of a trial handed to no worker yet (the rest of a round, a retried trial), or
    of ``theta`` (the told ``Trial``'s parameters, shape (D,); None for a tell by number) other
    than the parameters the study asked for. ``run_dir`` is named in the errors."""
    number = pending.number
    if pending.worker is None:  # made by a round (or a retry) and handed to nobody: no worker evaluated it
        raise ConfigError(f"trial {number} has not been handed to a worker yet: ask for it first "
                          f"(ppprops ask {run_dir} --worker NAME; study.ask(worker=...))")
    if pending.worker and teller != pending.worker:  # a tell that names no worker is the unnamed worker's
        who = f"not {teller!r}" if teller else "and this tell names no worker"
        raise ConfigError(f"trial {number} is held by worker {pending.worker!r}, {who}: each worker tells the trials "
                          f"it asked for (ppprops tell --worker {pending.worker}; in Python the Trial that ask returned)")
    if theta is not None and not np.array_equal(np.asarray(theta, dtype=np.float64), pending.theta):
        raise ConfigError(f"trial {number} does not hold the parameters the study asked for: tell the trial that ask returned")


def failure_reason(failed: Any) -> str:
    """The reason of ``tell(failed=...)`` on one line (runs of white space made one space).
    Raises ConfigError when nothing is left."""
    reason = " ".join(str(failed).split())
    if not reason:
        raise ConfigError("a failed trial needs a reason (what went wrong, e.g. 'e-stop at 3.2 s')")
    return reason


def check_failed_alone(number: int, *told: object) -> None:
    """Refuse feedback told together with ``failed=`` for trial ``number`` (``told``: the returns,
    feedback, components and diagnostics given; None where not)."""
    if any(value is not None for value in told):
        raise ConfigError(f"trial {number}: tell either its feedback or that it failed, not both")


def told_candidate(pending: Trial, returns: float | Sequence[float] | None, components: Any, diagnostics: Any, *,
                   feedback: Feedback | None, eval_s: float | None, task: Task, codec: Codec) -> Candidate:  # fmt: skip
    """The candidate that trial ``pending`` becomes with the told values (``told_feedback``; or
    ``feedback``, evaluated already), its parameters and feedback encoded (paper Eq. 5, 7-8).
    Raises ConfigError as ``check_episode_count`` and ``told_feedback`` do."""
    from .client.codec import encode_feedback

    if feedback is None and returns is not None and pending.seeds:
        check_episode_count(pending.number, len(pending.seeds), returns)
    fb = feedback if feedback is not None else told_feedback(returns, components, diagnostics, task=task.name,
                                                             declared_components=task.components,
                                                             declared_diagnostics=task.diagnostics)  # fmt: skip
    return Candidate(index=pending.number, iteration=pending.iteration, source=pending.source, params=pending.theta,
                     params_enc=codec.encode(pending.theta), feedback=fb, feedback_enc=encode_feedback(codec, fb),
                     clipped=pending.clipped, seeds=pending.seeds, note=pending.note, ask_s=pending.ask_s, eval_s=eval_s,
                     reevaluates=pending.reevaluates)  # fmt: skip


def check_episode_count(number: int, asked: int, returns: Any) -> None:
    """Refuse fewer returns than the ``asked`` episodes (the trial's seeds) of trial ``number``:
    less evidence than the study planned. More are welcome: their mean is used."""
    given = len(returns_list(returns))
    if 0 < given < asked:
        raise ConfigError(f"trial {number} asked for {asked} episodes (its seeds) and {given} "
                          f"return(s) were told: tell one return per episode (ppprops tell --stdin: "
                          '{"returns": [...]}), or create the study with the --episodes you run')


def told_feedback(returns: float | Sequence[float] | None, components: Any, diagnostics: Any, *, task: str,
                  declared_components: Collection[str], declared_diagnostics: Collection[str]) -> Feedback:
    """The told values as one ``Feedback``: the mean over the episodes given (module docstring).

    ``returns``: a number or one per episode; ``components`` / ``diagnostics``: None, one mapping
    (one episode), or one mapping per episode. ``task`` names the task in the errors. Raises
    ConfigError for no return, a return, component or diagnostic that is not a finite number (a
    diagnostic may be a text, but ``episode_length`` is a number of steps, >= 0), a declared
    component missing, an undeclared component or diagnostic, or a count of mappings that is not
    the count of returns."""
    if returns is None:
        raise ConfigError("tell needs the episode return(s) (or a Feedback)")
    rets = returns_list(returns)
    if not rets:
        raise ConfigError("tell needs at least one episode return")
    n = len(rets)
    comps = per_episode(components, n, "components")
    diags = per_episode(diagnostics, n, "diagnostics")
    declared_c, declared_d = set(declared_components), set(declared_diagnostics)
    episodes = []
    for i, r in enumerate(rets):
        if not _finite_number(r):
            raise ConfigError(f"episode return {r!r} is not a finite number")
        c = dict(comps[i])
        missing, unknown = sorted(declared_c - set(c)), sorted(set(c) - declared_c)
        if unknown:
            raise ConfigError(f"unknown component {unknown[0]!r}; task {task} declares: {', '.join(sorted(declared_c)) or 'none'}")
        if missing:
            raise ConfigError(f"component {missing[0]!r} is missing; task {task} declares: {', '.join(sorted(declared_c))}")
        for k, v in c.items():
            if not _finite_number(v):
                raise ConfigError(f"component {k!r} = {v!r} is not a finite number")
        d = dict(diags[i])
        unknown = sorted(set(d) - declared_d)
        if unknown:
            raise ConfigError(f"unknown diagnostic {unknown[0]!r}; task {task} declares: {', '.join(sorted(declared_d))}")
        for k, v in d.items():
            steps = k == "episode_length"  # the one diagnostic whose meaning is fixed: the episode's steps
            if isinstance(v, str) and not steps:
                continue
            if not _finite_number(v) or (steps and float(v) < 0):
                what = "not a number of steps" if steps else "neither a finite number nor a text"
                raise ConfigError(f"diagnostic {k!r} = {v!r} is {what}")
        episodes.append(Episode(ret=float(r), components={k: float(v) for k, v in c.items()},
                                diagnostics={k: (v if isinstance(v, str) else float(v)) for k, v in d.items()}))
    return aggregate(episodes)


def returns_list(returns: Any) -> list[Any]:
    """``returns`` as a list: one value (a number, or anything that is not a sequence of them: a text
    is one value, not its characters), or the values of a sequence."""
    if isinstance(returns, (str, bytes, Mapping)) or not isinstance(returns, Iterable):
        return [returns]
    if isinstance(returns, np.ndarray) and returns.ndim == 0:
        return [returns.item()]
    return list(returns)


def per_episode(values: Any, n: int, what: str) -> list[Mapping[str, Any]]:
    """``values`` (None, one mapping, or one mapping per episode) as ``n`` mappings; ``what`` names
    them in the error. Raises ConfigError when their count is not ``n``."""
    if values is None:
        return [{}] * n
    if isinstance(values, Mapping):
        if n != 1:
            raise ConfigError(f"{n} episode returns but one set of {what}: give one mapping per episode")
        return [values]
    out = list(values)
    if len(out) != n or not all(isinstance(v, Mapping) for v in out):
        raise ConfigError(f"{what}: give one mapping per episode ({n} episode returns)")
    return out


def _finite_number(v: Any) -> bool:
    """A finite int or float (numpy's too), not a bool."""
    return not isinstance(v, bool) and isinstance(v, (int, float, np.floating, np.integer)) and math.isfinite(float(v))
