"""The provider's clock: what the arrival times of a run's requests tell about its raw values.

The provider sees when each request arrives and when it answered. The gap between an answer and
the next request is the client's time: evaluating the candidate that answer proposed, telling it,
asking the next. On a rig whose evaluation time follows the episode (a real-time robot; a
simulator, less so), that gap follows the candidate's episode steps, hence its raw return on
tasks whose return is a function of the length (CartPole: the length). ``measure`` reads the
run's recorded request times (``llm_calls.sent``, or ``created - latency_s`` for calls recorded
before requests were written ahead) and the candidates told between an answer and the next
request, and reports:

- ``rho_steps`` / ``rho_return``: the Spearman correlation of the gaps with the candidates' episode
  steps (``episode_length`` x episodes, where the task reports it; else the evaluation time) and
  with their raw returns: what a provider would see once it knows what to look for. Under
  ``--parallel`` P a round's requests leave together after its P trials are told, so a gap
  follows the round's longest trial (or their sum, evaluated one after another) and its best;
- ``p``: how likely a correlation this strong is without any relation (two-sided, normal
  approximation of Spearman's rho under independence);
- ``best_error``: the relative error of the best shown candidate's raw return as the gap gives it,
  with the gap calibrated on the run itself (least squares of the raw return on the gap: the best
  calibration a provider could make, so an upper bound on what the clock gives);
- ``c_error``: under a pure reward scale (no warp, no offset), the error of c = median of
  printed / estimated raw return against the key; ``prior_c_error`` that of c = 1.

Findings (``privacy.audit``): a channel when the correlation is significant (p < ``SIGNIFICANT``),
exposed when the calibrated clock gives the best shown raw return within 1%.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..values import Candidate

SIGNIFICANT = 0.01
MIN_GAPS = 6


@dataclass
class Timing:
    """What the provider's clock gives on one run (see the module docstring); ``gaps`` in seconds."""

    gaps: list[float]
    steps: list[float]
    returns: list[float]
    rho_steps: float
    rho_return: float
    p: float
    best_error: float | None
    c_error: float | None = None
    prior_c_error: float | None = None

    @property
    def significant(self) -> bool:
        """The gaps follow the steps or the return beyond chance (p < SIGNIFICANT)."""
        return self.p < SIGNIFICANT

    def describe(self) -> str:
        """One line: the correlation over the gaps, and what the calibrated clock gives."""
        text = (f"the gaps between an answer and the next request follow the client's evaluation: Spearman {self.rho_steps:+.2f} "
                f"with the episode steps and {self.rho_return:+.2f} with the raw return over {len(self.gaps)} gaps (p = {self.p:.2g})")
        if self.best_error is not None:
            text += f"; calibrated, the gap gives the best shown raw return within {100 * self.best_error:.3g}%"
        if self.c_error is not None:
            text += f" and c within {100 * self.c_error:.3g}% (prior {100 * (self.prior_c_error or 0):.3g}%)"
        return text


def _ranks(x: Sequence[float]) -> np.ndarray:
    """Ranks from 1, ties given their mean rank."""
    a = np.asarray(x, dtype=np.float64)
    order = np.argsort(a, kind="mergesort")
    r = np.empty(len(a))
    r[order] = np.arange(1, len(a) + 1)
    for v in np.unique(a):
        tie = a == v
        if tie.sum() > 1:
            r[tie] = r[tie].mean()
    return r


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation of ``x`` and ``y`` (0 when either is constant)."""
    rx, ry = _ranks(x), _ranks(y)
    if np.std(rx) == 0 or np.std(ry) == 0:
        return 0.0
    return float(np.corrcoef(rx, ry)[0, 1])


def _p_value(rho: float, n: int) -> float:
    """Two-sided p of Spearman's rho under independence (normal approximation, z = rho sqrt(n - 1))."""
    z = abs(rho) * math.sqrt(max(n - 1, 1))
    return math.erfc(z / math.sqrt(2))


def _steps(c: Candidate) -> float:
    length = c.feedback.diagnostics.get("episode_length")
    if isinstance(length, (int, float)) and math.isfinite(length):
        return float(length) * max(1, len(c.seeds))
    return float(c.eval_s) if c.eval_s is not None else math.nan


def pairs(calls: Sequence[dict[str, Any]], told: Sequence[tuple[float, Candidate]], width: int = 1) -> list[tuple[float, list[Candidate]]]:
    """(gap, batch) for each request that leaves after a batch of 1 to ``width`` candidates was told
    since the last answer before it (``told``: (when it was recorded, Unix s; the candidate)): the
    gap, in seconds, from that answer to the request's arrival. At ``width`` 1 a batch is the one
    candidate the answer proposed; at ``--parallel`` P, the round's P requests leave together once
    the last of its P trials is told, so each round gives one gap and its batch (later requests of
    the same round add nothing). Retries are left out (their gap is the client's own back-off)."""
    times = []
    for c in calls:
        sent = c.get("sent")
        if sent is None:
            sent = float(c.get("created") or 0.0) - float(c.get("latency_s") or 0.0)
        times.append((float(sent), c))
    times.sort(key=lambda t: t[0])
    answers = sorted((sent + float(c.get("latency_s") or 0.0), i) for i, (sent, c) in enumerate(times)
                     if c.get("ok") and c.get("answered", True))
    out: list[tuple[float, list[Candidate]]] = []
    used: set[float] = set()
    for j, (nxt, n) in enumerate(times):
        if int(n.get("retry") or 0) != 0:
            continue
        before = [a for a, i in answers if a <= nxt and i != j]
        if not before or before[-1] in used:
            continue
        answer = before[-1]
        batch = [k for when, k in told if answer <= when <= nxt]
        if 1 <= len(batch) <= width:
            used.add(answer)
            out.append((nxt - answer, batch))
    return out


def measure(calls: Sequence[dict[str, Any]], told: Sequence[tuple[float, Candidate]], shown: Sequence[int], *,
            c: float | None = None, pure_scale: bool = False, width: int = 1) -> Timing | str:
    """The provider's clock on one run, or why it cannot be measured (fewer than ``MIN_GAPS`` gaps).

    ``told``: (when recorded, candidate) of every candidate; ``shown``: indices of the candidates some request showed (the best of them is scored);
    ``c``: the true reward scale, scored when ``pure_scale`` (r~ = c r); ``width``: the run's
    ``--parallel`` P. A round's gap is set by its trials together: by the longest when they are
    evaluated side by side, by their sum when one after another; both are measured and the closer
    one reported, and the gap is scored against the round's best raw return (the longest episode
    on tasks whose return is the length)."""
    got = [(g, ks) for g, ks in pairs(calls, told, width) if all(math.isfinite(k.ret) for k in ks)]
    if len(got) < MIN_GAPS:
        return f"{len(got)} gaps between an answer and the next request (needs {MIN_GAPS})"
    gaps = [g for g, _ in got]
    best_of = [max(ks, key=lambda k: k.ret) for _, ks in got]
    rets = [float(k.ret) for k in best_of]
    rho_s, n_s, chosen = 0.0, 0, [math.nan] * len(got)
    for combine in (max, sum):
        steps = [float(combine(_steps(k) for k in ks)) for _, ks in got]
        finite = [i for i, st in enumerate(steps) if math.isfinite(st)]
        rho = spearman([gaps[i] for i in finite], [steps[i] for i in finite]) if len(finite) >= MIN_GAPS else 0.0
        if n_s == 0 or abs(rho) > abs(rho_s):
            rho_s, n_s, chosen = rho, len(finite), steps
    rho_r = spearman(gaps, rets)
    p = min(_p_value(rho_s, n_s) if n_s >= MIN_GAPS else 1.0, _p_value(rho_r, len(gaps)))
    A = np.column_stack([gaps, np.ones(len(gaps))])
    coef, *_ = np.linalg.lstsq(A, np.asarray(rets), rcond=None)
    est = A @ coef
    in_shown = [i for i, k in enumerate(best_of) if k.index in set(shown)]
    best_error = None
    if in_shown:
        b = max(in_shown, key=lambda i: rets[i])
        best_error = abs(float(est[b]) - rets[b]) / abs(rets[b]) if rets[b] else None
    t = Timing(gaps, chosen, rets, rho_s, rho_r, p, best_error)
    if pure_scale and c is not None:
        enc = np.asarray([float(k.feedback_enc.ret) for k in best_of])
        ok = np.abs(est) > 1e-9
        if ok.any():
            c_hat = float(np.median(enc[ok] / est[ok]))
            if c_hat > 0:
                t.c_error = float(np.expm1(abs(math.log(c_hat / c))))
                t.prior_c_error = float(np.expm1(abs(math.log(1.0 / c))))
    return t
