"""Attacks that use only a run's transcript (the recorded request bodies) and public knowledge.

Each attack estimates one secret of the paper's scheme from what the provider saw: the reward
scale c, or the parameter scales a_j. It reads nothing from the store but the request bodies,
and knows only what docs/threat-model.md grants the provider (the task, its public box, its
reward structure and time limit, the warm-up procedure, this open-source code). Results are
compared with the true secrets afterwards, by ``ppprops.privacy.report``.

Reward scale c: ``diagnostic`` (a diagnostic that determines the return, e.g. CartPole's
episode length), ``lattice`` (integer returns: the gcd of differences of printed returns),
``known-cap`` (a return at a public cap, e.g. CartPole's 500 at the time limit).
Parameter scales a: ``warmup-range`` (uniform warm-up from the public box: max |theta~_j| / 6),
``stated-range`` (a range stated in the prompt for the shown coordinates), ``clip-edge``
(answers clipped to the box re-encode to exactly a_j times the bound, and repeat), and
``seed-replay`` (the request's sampling seed gives away a small run seed; the warm-up drawn from
it is then replayed, raw, and divided into the shown values).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .. import seeding
from .audit import token_value
from .knowledge import PublicFacts, facts_for
from .transcript import Request

SEED_SEARCH = 1 << 16  # run seeds tried against the request's sampling seed
SEED_SEARCH_BLIND = 2048  # run seeds tried when no sampling seed was sent (matched on signs)
WARMUP_REPLAY = 32  # warm-up samples replayed per seed


@dataclass(frozen=True)
class Shown:
    """One distinct history entry as the provider saw it."""

    params: np.ndarray
    tols: np.ndarray
    ret: float
    ret_tol: float
    diagnostics: dict[str, str]
    first_call: int


@dataclass(frozen=True)
class View:
    """Everything an attack may use: the transcript and public facts."""

    requests: tuple[Request, ...]
    entries: tuple[Shown, ...]
    warmup: tuple[Shown, ...]  # the entries of the first request: the warm-up, as Algorithm 1 starts
    facts: PublicFacts
    box: tuple[float, float]
    D: int


@dataclass(frozen=True)
class Estimate:
    attack: str
    target: str  # "c" or "a"
    value: float | np.ndarray | None  # None: the attack found nothing; a: NaN where not estimated
    detail: str = ""

    @property
    def applicable(self) -> bool:
        if self.value is None:
            return False
        return bool(np.any(np.isfinite(np.atleast_1d(self.value))))


def view_of(requests: Sequence[Request], task: str, box: tuple[float, float]) -> View:
    seen: dict[tuple[tuple[str, ...], str], Shown] = {}
    first: list[Shown] = []
    D = 0
    for k, r in enumerate(requests):
        for e in r.entries:
            parsed = [token_value(t) for t in e.params]
            ret = token_value(e.ret)
            if ret is None or any(p is None for p in parsed) or not parsed:
                continue
            D = max(D, len(parsed))
            key = (e.params, e.ret)
            if key not in seen:
                seen[key] = Shown(np.array([p[0] for p in parsed if p]), np.array([p[1] for p in parsed if p]),
                                  ret[0], ret[1], dict(e.diagnostics), k)
            if k == 0:
                first.append(seen[key])
    entries = tuple(s for s in seen.values() if len(s.params) == D)
    return View(tuple(requests), entries, tuple(s for s in first if len(s.params) == D), facts_for(task), box, D)


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
            raw = sum(coef * x[0] for coef, x in zip(formula.values(), vals, strict=True) if x) + v.facts.formula_const
            if raw != 0:
                f.append(raw), r.append(e.ret), tol.append(e.ret_tol)
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
                return Estimate("lattice", "c", c_est, f"{len(vals)} distinct returns on a lattice of step {c_est:.6g}")
    return Estimate("lattice", "c", None, "the printed returns lie on no lattice")


def known_cap(v: View) -> Estimate:
    """c = printed return / cap, for entries a diagnostic (or a tie at the extreme) marks as capped."""
    for side, cap, diag, marker in v.facts.caps:
        hits = [e.ret for e in v.entries if _same(e.diagnostics.get(diag), marker)]
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


def _same(printed: str | None, marker: str) -> bool:
    if printed is None:
        return False
    if printed == marker:
        return True
    a, b = token_value(printed), token_value(marker)
    return a is not None and b is not None and a[0] == b[0]


# -- parameter scales ------------------------------------------------------------------------------
def warmup_range(v: View) -> Estimate:
    """a_j from the spread of the warm-up, drawn uniformly from the public box (Algorithm 1)."""
    n = len(v.warmup)
    if n < 2:
        return Estimate("warmup-range", "a", None, "fewer than two warm-up entries")
    X = np.array([e.params for e in v.warmup])
    lo, hi = v.box
    if np.isclose(lo, -hi):
        a = np.max(np.abs(X), axis=0) * (n + 1) / n / hi
    else:
        a = (X.max(axis=0) - X.min(axis=0)) * (n + 1) / (n - 1) / (hi - lo)
    return Estimate("warmup-range", "a", a, f"{n} warm-up entries, unbiased range estimate")


_RANGE = re.compile(r"(?:must lie in|drawn uniformly from) \[([^\],]+), ([^\]]+)\]")


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
    lo, hi = v.box
    X = np.array([e.params for e in v.entries]) if v.entries else np.zeros((0, v.D))
    a = np.full(v.D, np.nan)
    for j in range(v.D if len(X) else 0):
        for sign, bound in ((1.0, hi), (-1.0, lo)):
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
    lo, hi = v.box
    first = v.requests[0]
    seeds: Sequence[int] = range(SEED_SEARCH_BLIND)
    how = f"tried run seeds 0..{SEED_SEARCH_BLIND - 1} on signs"
    if first.seed is not None:
        found = next((s for s in range(SEED_SEARCH) if seeding.llm_seed(s, first.iteration, first.attempt) == first.seed), None)
        if found is not None:
            seeds, how = [found], f"run seed {found} recovered from the request's sampling seed"
    W = np.array([e.params for e in v.warmup])
    tol = np.array([e.tols for e in v.warmup])
    for s in seeds:
        raw = np.array([seeding.rng(s, seeding.WARMUP, m).uniform(lo, hi, size=v.D) for m in range(WARMUP_REPLAY)])
        pairs = []
        for i, w in enumerate(W):
            live = np.abs(w) > tol[i]
            match = [m for m in range(len(raw)) if np.all(np.sign(raw[m][live]) == np.sign(w[live]))]
            if len(match) == 1:
                pairs.append((i, match[0]))
        if len(pairs) < min(3, len(W)):
            continue
        num = sum(W[i] * raw[m] for i, m in pairs)
        den = sum(raw[m] ** 2 for _, m in pairs)
        a = num / den
        resid = max(float(np.max(np.abs(W[i] - a * raw[m]) - 2 * tol[i] - 0.02 * np.abs(W[i]))) for i, m in pairs)
        if resid <= 0 and np.all(a > 0):
            return Estimate("seed-replay", "a", a, f"{how}; {len(pairs)} warm-up entries replayed")
    return Estimate("seed-replay", "a", None, f"{how}: no replay matches the warm-up")


ATTACKS: dict[str, Callable[[View], Estimate]] = {
    "diagnostic": diagnostic,
    "lattice": lattice,
    "known-cap": known_cap,
    "warmup-range": warmup_range,
    "stated-range": stated_range,
    "clip-edge": clip_edge,
    "seed-replay": seed_replay,
}


def run_attacks(requests: Sequence[Request], task: str, box: tuple[float, float]) -> list[Estimate]:
    """Every attack on one transcript."""
    v = view_of(requests, task, box)
    return [f(v) for f in ATTACKS.values()]
