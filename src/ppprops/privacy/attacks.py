"""Attacks that use only a run's transcript (the recorded request bodies) and public knowledge.

Each attack estimates one secret of the paper's scheme from what the provider saw: the reward
scale c, or the parameter scales a_j. It reads nothing from the store but the request bodies,
and knows only what docs/threat-model.md grants the provider (the task, its public box, its
reward structure and time limit, the warm-up procedure, this open-source code). Results are
compared with the true secrets afterwards, by ``ppprops.privacy.matrix``.

Reward scale c: ``diagnostic`` (a diagnostic that determines the return, e.g. CartPole's
episode length), ``lattice`` (integer returns: the gcd of differences of printed returns),
``warped-lattice`` (integer returns through an unknown power warp and offset), ``known-cap`` (a
return at a public cap, e.g. CartPole's 500 at the time limit), ``additivity`` (the return is the
sum of the components), ``survive-length`` and ``saturated-ctrl`` (locomotion components with
public per-step values); the last four are in ``reward_attacks``.
Parameter scales a: ``warmup-range`` (uniform warm-up from the public box: max |theta~_j| / 6),
``stated-range`` (a range stated in the prompt for the shown coordinates), ``clip-edge``
(answers clipped to the box re-encode to exactly a_j times the bound, and repeat),
``seed-replay`` (a run seed found from the request's sampling seed or by trying small seeds
against the warm-up's signs; the warm-up drawn from it is then replayed, raw, and divided into
the shown values) and ``fallback-spread`` (fallback candidates: the best policy plus noise of a
public width, replayed from the run seed or measured by its spread).
Simulator attacks (``privacy.simfit``; they also build the task's env when it is public, within a
bound): ``sim-exact`` / ``sim-exact-a`` (initial states known: c, a and the raw values) and
``sim-marginal`` / ``sim-marginal-a`` (over the public initial-state distribution), and
``sim-marginal-lattice`` (c from the same fit by the exact likelihood of integer returns).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from .. import seeding
from ..errors import ConfigError
from ..plugins import load_plugins
from ..proposers.llm import FALLBACK_SIGMA
from . import simfit
from .requests import Request
from .reward_attacks import additivity, saturated_ctrl, survive_length, warped_lattice
from .runseed import RANGE_STATED as _RANGE
from .runseed import find_run_seed, replay_scale
from .simfit import SimLimits, sim_exact, sim_exact_a, sim_marginal, sim_marginal_a, sim_marginal_lattice
from .tokens import token_value
from .view import Estimate, Shown, View, same_marker, view_of

if TYPE_CHECKING:
    from ..tasks.base import Task



# -- reward scale ----------------------------------------------------------------------------
def diagnostic(v: View) -> Estimate:
    """c from a diagnostic that determines the raw return (public formula, else a constant ratio)."""
    formula = v.facts.return_formula
    if formula:
        f, r, tol = [], [], []
        for e in v.entries:
            vals = [token_value(e.diagnostics[k]) if k in e.diagnostics else None for k in formula]
            if any(x is None for x in vals):
                continue
            raw = sum(coef * x[0] for coef, x in zip(formula.values(), vals, strict=True) if x) + (v.facts.return_formula_constant or 0.0)
            if raw != 0:
                f.append(raw)
                r.append(e.ret)
                tol.append(e.ret_tol)
        if len(f) >= 2:
            fa, ra = np.array(f), np.array(r)
            c = float(fa @ ra / (fa @ fa))
            if c > 0 and np.max(np.abs(ra - c * fa)) <= 2 * max(tol) + 1e-3 * np.max(np.abs(ra)):
                return Estimate("diagnostic", "c", c, f"return = {formula} holds on {len(f)} entries")
    for name in sorted({k for e in v.entries for k in e.diagnostics}):
        ratios = []
        for e in v.entries:
            d = token_value(e.diagnostics.get(name, ""))
            if d is not None and d[0] != 0:
                ratios.append(e.ret / d[0])
        if len(ratios) >= 3:
            med = float(np.median(ratios))
            if med > 0 and (max(ratios) - min(ratios)) <= 0.01 * abs(med):
                return Estimate("diagnostic", "c", med, f"printed return / {name} is constant on {len(ratios)} entries")
    return Estimate("diagnostic", "c", None, "no diagnostic determines the printed return")


def lattice(v: View) -> Estimate:
    """c as the largest step of which every difference of printed returns is a whole multiple."""
    if not v.facts.integer_returns:
        return Estimate("lattice", "c", None, "returns of this task are not known to be integers")
    vals = np.array(sorted({e.ret for e in v.entries}))
    if len(vals) < 5:
        return Estimate("lattice", "c", None, f"only {len(vals)} distinct returns")
    tol = max(e.ret_tol for e in v.entries)
    d = vals - vals[0]
    c_min = 10 * tol
    gaps = sorted(set(np.round(np.diff(vals), 12)))[:6]
    trials = sorted({g / n for g in gaps for n in range(1, 2001) if g / n >= c_min}, reverse=True)
    order = np.argsort(d)
    for tried, c0 in enumerate(trials, 1):
        c_est, ks = c0, np.zeros(len(d))
        ok = True
        for i in order[1:]:
            ks[i] = np.round(d[i] / c_est)
            if ks[i] < 1:
                ok = False
                break
            mask = ks > 0
            c_est = float(ks[mask] @ d[mask] / (ks[mask] @ ks[mask]))
        if not ok or len(set(ks)) < len(ks):
            continue
        if np.max(np.abs(d - ks * c_est)) <= 2.02 * tol + 1e-9:
            # how likely a step this large fits every difference by chance, over the steps tried so far
            chance = (4 * tol / c_est) ** (len(vals) - 2) * tried
            if chance < 0.01:
                return Estimate("lattice", "c", c_est, f"{len(vals)} distinct returns on one lattice")
    return Estimate("lattice", "c", None, "the printed returns lie on no lattice")


def known_cap(v: View) -> Estimate:
    """c = printed return / cap, for entries a diagnostic (or a tie at the extreme) marks as capped."""
    for known in v.facts.caps or ():
        side, cap, diag, marker = known.side, known.value, known.diagnostic, known.marker
        hits = [e.ret for e in v.entries if same_marker(e.diagnostics.get(diag), marker)]
        how = f"{diag}={marker}"
        if not hits:
            rets = [e.ret for e in v.entries]
            if not rets:
                continue
            edge = max(rets) if side == "max" else min(rets)
            tied = [e for e in v.entries if e.ret == edge]
            if len({tuple(e.params) for e in tied}) >= 2:
                hits, how = [edge] * len(tied), f"{len(tied)} policies tie at the {side}"
        if hits:
            c = float(np.median(hits)) / cap
            if c > 0:
                return Estimate("known-cap", "c", c, f"{len(hits)} entries at the public cap {cap:g} ({how})")
    return Estimate("known-cap", "c", None, "no entry is known to sit at a public cap")


# -- parameter scales ------------------------------------------------------------------------------
def warmup_range(v: View) -> Estimate:
    """a_j from the spread of the warm-up, drawn uniformly from the public box (Algorithm 1)."""
    n = len(v.warmup)
    if n < 2:
        return Estimate("warmup-range", "a", None, "fewer than two warm-up entries")
    X = np.array([e.params for e in v.warmup])
    lo, hi = v.init_box  # the public box, or an MLP's scaled initialisation per layer
    if np.all(np.isclose(lo, -hi)):
        a = np.max(np.abs(X), axis=0) * (n + 1) / n / hi
    else:
        a = (X.max(axis=0) - X.min(axis=0)) * (n + 1) / (n - 1) / (hi - lo)
    return Estimate("warmup-range", "a", a, f"{n} warm-up entries, unbiased range estimate")


def stated_range(v: View) -> Estimate:
    """a_j from a range the prompt states for the shown coordinates, against the public box."""
    for r in v.requests:
        m = _RANGE.search(r.text)
        if m:
            lo, hi = token_value(m.group(1)), token_value(m.group(2))
            if lo and hi and hi[0] > lo[0]:
                a = (hi[0] - lo[0]) / (v.box[1] - v.box[0])
                return Estimate("stated-range", "a", np.full(v.D, a), f"the prompt states [{m.group(1)}, {m.group(2)}]")
    return Estimate("stated-range", "a", None, "no range stated for the shown coordinates")


def clip_edge(v: View) -> Estimate:
    """a_j = |edge| / bound where different policies print exactly the same extreme value of a coordinate.

    Answers outside the box are clipped and re-encoded to exactly a_j times the bound, so the edge
    repeats to the last digit across policies that differ elsewhere (at least half their coordinates).
    """
    lo, hi = (np.broadcast_to(np.asarray(b, dtype=np.float64), (v.D,)) for b in v.layer_box)  # an MLP: per layer
    X = np.array([e.params for e in v.entries]) if v.entries else np.zeros((0, v.D))
    a = np.full(v.D, np.nan)
    for j in range(v.D if len(X) else 0):
        for sign, bound in ((1.0, hi[j]), (-1.0, lo[j])):
            if sign * bound <= 0:
                continue
            col = sign * X[:, j]
            top = col.max()
            if top <= 0:
                continue
            at = np.flatnonzero(col == top)
            rows = [np.delete(X[i], j) for i in at]
            distinct = any(np.sum(r1 != r2) >= len(r1) / 2 for k, r1 in enumerate(rows) for r2 in rows[k + 1:])
            if distinct:
                est = top / abs(bound)
                a[j] = est if np.isnan(a[j]) else min(a[j], est)
    found = int(np.sum(np.isfinite(a)))
    if not found:
        return Estimate("clip-edge", "a", None, "no coordinate repeats an extreme value across different policies")
    return Estimate("clip-edge", "a", a, f"{found} of {v.D} coordinates sit at a repeated edge")


def seed_replay(v: View) -> Estimate:
    """Find the run seed (from the request's sampling seed, else by trying small seeds), replay the warm-up."""
    if not v.warmup:
        return Estimate("seed-replay", "a", None, "no warm-up entries")
    seed, how = find_run_seed(v)
    if seed is None:
        return Estimate("seed-replay", "a", None, how)
    a, why = replay_scale(v, seed)
    if a is None:
        return Estimate("seed-replay", "a", None, f"{how}; {why}")
    return Estimate("seed-replay", "a", a, f"{how}; {why}")


def fallback_spread(v: View) -> Estimate:
    """a_j from fallback candidates: the best shown policy plus noise of a public width (5% of the box).

    Fallbacks are the entries that follow an iteration whose last answer was unusable (the provider
    knows: it gave that answer). Drawn in raw space, their encoded offsets from the best are a_j times the noise: with the
    run seed the noise itself is replayed (seeding.FALLBACK), else its spread gives a_j. Drawn in the
    encoded space, both give the public width back, i.e. a_j = 1 whatever a_j is.
    """
    shown_before: list[Shown] = []
    offsets, iters = [], []
    warm = {id(e) for e in v.warmup}
    by_call: dict[int, list[Shown]] = {}
    for e in v.entries:
        by_call.setdefault(e.first_call, []).append(e)
    for k, r in enumerate(v.requests):
        # the candidate new in request k came from the iteration before: the provider's own answer
        # unless its last answer there was unusable (then the client sent a fallback)
        before = [q for q in v.requests[:k] if q.iteration == r.iteration - 1]
        fallback = bool(before) and _answer_vector(before[-1].answer, v.D) is None
        for e in by_call.get(k, []):
            if id(e) in warm or not shown_before or not fallback:
                continue
            best = max(shown_before, key=lambda x: x.ret)
            offsets.append(e.params - best.params)
            iters.append(r.iteration - 1)
        shown_before += by_call.get(k, [])
    if not offsets:
        return Estimate("fallback-spread", "a", None, "no fallback candidate in the history")
    lo, hi = v.layer_box  # an MLP's fallback noise is 5% of each layer box's width
    sigma = FALLBACK_SIGMA * (hi - lo)
    X = np.array(offsets)
    seed, how = find_run_seed(v)
    if seed is not None:
        Z = np.array([seeding.rng(seed, seeding.FALLBACK, it).normal(0.0, sigma, size=v.D) for it in iters])
        with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # coordinates without a usable draw stay NaN
            ratio = np.where(np.abs(Z) > 0.2 * sigma, X / Z, np.nan)
            a = np.nanmedian(np.where(ratio > 0, ratio, np.nan), axis=0)
        return Estimate("fallback-spread", "a", a, f"{len(X)} fallbacks, noise replayed ({how})")
    if len(X) < 3:
        return Estimate("fallback-spread", "a", None, f"only {len(X)} fallbacks and no run seed to replay their noise")
    a = np.sqrt(np.mean(X**2, axis=0)) / sigma
    return Estimate("fallback-spread", "a", a, f"spread of {len(X)} fallbacks around the best shown policy")


def _answer_vector(answer: str | None, D: int) -> np.ndarray | None:
    """The vector an answer gives, read as the client reads it (``wire.parse_answer``), or None."""
    from ..wire import parse_answer

    result = parse_answer(answer or "", D)
    return None if result.values is None else np.array(result.values)


ATTACKS: dict[str, Callable[[View], Estimate]] = {
    "diagnostic": diagnostic,
    "lattice": lattice,
    "warped-lattice": warped_lattice,
    "known-cap": known_cap,
    "additivity": additivity,
    "survive-length": survive_length,
    "saturated-ctrl": saturated_ctrl,
    "warmup-range": warmup_range,
    "stated-range": stated_range,
    "clip-edge": clip_edge,
    "seed-replay": seed_replay,
    "fallback-spread": fallback_spread,
    "sim-exact": sim_exact,
    "sim-exact-a": sim_exact_a,
    "sim-marginal": sim_marginal,
    "sim-marginal-lattice": sim_marginal_lattice,
    "sim-marginal-a": sim_marginal_a,
}
# The secret each attack estimates: "c" (the reward scale) or "a" (the parameter scales a_j).
TARGET: dict[str, str] = {
    **dict.fromkeys(("diagnostic", "lattice", "warped-lattice", "known-cap", "additivity", "survive-length", "saturated-ctrl",
                     "sim-exact", "sim-marginal", "sim-marginal-lattice"), "c"),
    **dict.fromkeys(("warmup-range", "stated-range", "clip-edge", "seed-replay", "fallback-spread", "sim-exact-a",
                     "sim-marginal-a"), "a"),
}
# Attacks that simulate the task's env (bounded by ``simfit.SimLimits``); the others read the transcript alone.
SIMULATOR_ATTACKS = frozenset({"sim-exact", "sim-exact-a", "sim-marginal", "sim-marginal-lattice", "sim-marginal-a"})
assert TARGET.keys() == ATTACKS.keys()


def register_attack(name: str, target: str, attack: Callable[[View], Estimate]) -> None:
    """Add ``attack`` to every privacy report of this process (``ppprops privacy-report``, ``run_attacks``).

    ``attack(view)`` reads only the provider's view of one transcript (``privacy.view.View``) and
    returns an ``Estimate`` named ``name`` of the secret ``target``: ``"c"`` (a float) or ``"a"``
    (an array of shape (D,), NaN where not estimated), or ``value=None`` when it finds nothing.
    Another process (a shell's ``ppprops privacy-report``) runs it only if it registers it too:
    call this from a module named by a ``ppprops.plugins`` entry point of an installed package
    (``ppprops.plugins``; docs/architecture.md, "Recipe: add a privacy attack").
    Raises ConfigError (as ``methods.register_method`` does) for a taken name or another target.
    """
    if name in ATTACKS:
        raise ConfigError(f"an attack named {name!r} is already registered")
    if target not in ("c", "a"):
        raise ConfigError(f"an attack estimates 'c' or 'a', not {target!r}")
    ATTACKS[name] = attack
    TARGET[name] = target


def run_attacks(requests: Sequence[Request], task: str | Task, box: tuple[float, float], *,
                limits: SimLimits | None = None, simulate: bool | None = None) -> list[Estimate]:
    """Every registered attack on one transcript (the recorded request bodies), in registry order.

    ``task``: the task's name, or the Task (its public declaration, from which the simulator
    attacks build its env when the env is public). ``limits`` bounds each simulator attack
    (default ``simfit.DEFAULT_LIMITS``). ``simulate``: run the simulator attacks (default: when
    ``task`` is a Task, as the audit and the report pass it; with a bare name they report "not
    run", so callers that only read the transcript stay fast). Loads the ``ppprops.plugins``
    entry points first (once per process), so the attacks of installed plugins run too. Raises
    ConfigError when a plugin fails to load.
    """
    if simulate is None:
        simulate = not isinstance(task, str)
    load_plugins()
    v = view_of(requests, task, box)
    v.memo["sim_limits"] = limits or simfit.DEFAULT_LIMITS
    out = []
    for name, f in ATTACKS.items():
        if name in SIMULATOR_ATTACKS and not simulate:
            out.append(Estimate(name, TARGET[name], None, "simulator attacks were not asked for",
                                not_run="simulator attacks were not asked for"))
            continue
        est = f(v)
        gone = v.facts.missing(*NEEDS_FACT.get(name, ()))
        if gone and est.value is None and not est.not_run:  # it found nothing because the task does not say
            est = replace(est, not_run=f"fact unknown: {', '.join(gone)} (not declared in the [privacy] table of task {v.facts.task})")
        out.append(est)
    return out


# The public facts each attack's premise needs (``tasks.facts.FACT_NAMES``, declared in a task file's
# [privacy] table); when the task leaves one unknown and the attack finds nothing, it reports
# "not run: fact unknown" instead of "found nothing".
NEEDS_FACT: dict[str, tuple[str, ...]] = {
    "lattice": ("integer_returns",),
    "warped-lattice": ("integer_returns", "return_range"),
    "known-cap": ("caps",),
    "diagnostic": ("return_formula",),
    "additivity": ("components_sum_to_return",),
    "survive-length": ("survive_component", "time_limit"),
    "saturated-ctrl": ("ctrl_component", "time_limit"),
}
