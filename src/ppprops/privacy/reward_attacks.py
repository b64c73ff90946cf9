"""Transcript-only attacks on the reward secrets beyond the paper's pure scale (docs/threat-model.md).

- ``warped-lattice``: integer returns under r~ = c (w_p(r) - w_p(s)). Three printed returns and
  hypothesised integer raw values fix p (a ratio of differences does not depend on c or s) and
  then c and s; the hypothesis holds when every other printed return decodes to an integer
  within the printed precision, refitted on all of them. A public cap (CartPole's 500, Acrobot's
  -500) is used as one of the three when a diagnostic marks it.
- ``additivity``: the printed return equals the sum of the printed components once decoded with
  one shared map; a fit of (c, s, p) to that equation on every entry, anchored by the survive
  component at the time limit (healthy reward x time limit) where a diagnostic marks it.
- ``survive-length``: locomotion under a pure scale: the survive component is the healthy reward
  times the episode length (or times the time limit, at the time limit), so c = printed / that.
- ``saturated-ctrl``: a controller saturated at the action bounds costs exactly ctrl_per_step per
  step; the most negative printed control cost per step, shared by several policies, is -c times it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from .tokens import token_value
from .view import Estimate, View, same_marker

MAX_HYPOTHESES = 600_000  # integer triples tried by the warped-lattice search
P_RANGE = (0.4, 2.5)  # exponents searched (the hardened prior is [0.5, 0.8] and [1.25, 2]; 1 is the paper's)


def _w(x: np.ndarray | float, p: np.ndarray | float) -> np.ndarray:
    return np.sign(x) * np.abs(x) ** p


# -- warped lattice ----------------------------------------------------------------------------
def warped_lattice(v: View) -> Estimate:
    """c (with s and p) from integer returns seen through an unknown power warp and offset."""
    f = v.facts
    name = "warped-lattice"
    if not f.integer_returns or not f.return_range:
        return Estimate(name, "c", None, "returns of this task are not known to be integers")
    lo, hi = f.return_range
    flip = hi <= 0  # work with |r| > 0: y' = -y = c (w(|r|) - w(-s)) for negative returns
    ys = sorted({(-e.ret if flip else e.ret) for e in v.entries})
    tol = max((e.ret_tol for e in v.entries), default=0.005)
    if len(ys) < 6:
        return Estimate(name, "c", None, f"only {len(ys)} distinct returns")
    qmax = int(max(abs(lo), abs(hi)))
    anchor = _cap_anchor(v, flip)
    Y = np.array(ys)
    if anchor is not None:
        y_a, q_a = anchor
        rest = [y for y in ys if y < y_a - tol]
        if len(rest) < 5:
            return Estimate(name, "c", None, "too few returns below the anchored cap")
        a, b = _pairs(qmax)
        refs = (rest[0], rest[1], y_a)
        triples = (a, b, np.full(len(a), float(q_a)))
        how = f"anchored at the public cap {q_a:g}"
    else:
        span = max(2, int(round((MAX_HYPOTHESES * 6) ** (1 / 3))))
        refs = (ys[0], ys[1], ys[2])
        triples = _triples(span)
        how = f"the three lowest returns tried as integers up to {span}"
    fits = _lattice_fits(Y, refs, triples, tol)
    n_hyp = len(triples[0])
    if not fits:
        return Estimate(name, "c", None, f"no warp maps the printed returns onto integers ({how}; {n_hyp} hypotheses)")
    c_vals = np.array([fit[0] for fit in fits])
    if np.max(c_vals) / np.min(c_vals) > 1.01:
        return Estimate(name, "c", None, f"{len(fits)} different warps fit equally ({how})")
    c_est, s_est, p_est, chance = fits[0]
    chance *= n_hyp
    if chance >= 0.01:
        return Estimate(name, "c", None, f"a fit exists but could be chance (expected {chance:.2g} by chance; {how})")
    s_est = -s_est if flip else s_est
    return Estimate(name, "c", c_est, f"{len(Y)} distinct returns decode to integers under one warp ({how})",
                    extras={"s": s_est, "p": p_est})


@functools.cache
def _triples(span: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every integer triple 1 <= a < b < c <= span (built once per process)."""
    g = np.arange(1, span + 1)
    a, b, c = np.meshgrid(g, g, g, indexing="ij")
    keep = (a < b) & (b < c)
    return a[keep].astype(float), b[keep].astype(float), c[keep].astype(float)


@functools.cache
def _pairs(qmax: int) -> tuple[np.ndarray, np.ndarray]:
    """Every integer pair 1 <= a < b < qmax."""
    g = np.arange(1, qmax)
    a, b = np.meshgrid(g, g, indexing="ij")
    keep = a < b
    return a[keep].astype(float), b[keep].astype(float)


def _cap_anchor(v: View, flip: bool) -> tuple[float, float] | None:
    """(printed value, |raw|) of a return a diagnostic marks as the public cap, if one is shown."""
    for cap in v.facts.caps or ():
        hits = {(-e.ret if flip else e.ret) for e in v.entries if same_marker(e.diagnostics.get(cap.diagnostic), cap.marker)}
        if len(hits) == 1:
            return hits.pop(), abs(cap.value)
    return None


def _lattice_fits(Y: np.ndarray, refs: tuple[float, float, float],
                  triples: tuple[np.ndarray, np.ndarray, np.ndarray], tol: float) -> list[tuple[float, float, float, float]]:
    """Hypotheses (integer raw values of three reference returns) whose warp decodes every return to an integer."""
    y1, y2, y3 = refs
    rho = (y3 - y1) / (y2 - y1)
    q1, q2, q3 = triples
    lo_p, hi_p = np.full(len(q1), math.log(P_RANGE[0])), np.full(len(q1), math.log(P_RANGE[1]))

    def ratio(lp: np.ndarray) -> np.ndarray:
        p = np.exp(lp)
        return (q3**p - q1**p) / (q2**p - q1**p)

    ok = (ratio(lo_p) - rho) * (ratio(hi_p) - rho) < 0
    q1, q2, q3, lo_p, hi_p = q1[ok], q2[ok], q3[ok], lo_p[ok], hi_p[ok]
    if not len(q1):
        return []
    increasing = ratio(hi_p) > ratio(lo_p)
    for _ in range(40):
        mid = (lo_p + hi_p) / 2
        above = (ratio(mid) > rho) == increasing
        hi_p = np.where(above, mid, hi_p)
        lo_p = np.where(above, lo_p, mid)
    p = np.exp((lo_p + hi_p) / 2)
    alpha = (q2**p - q1**p) / (y2 - y1)
    beta = q1**p - alpha * y1
    # loose screen: every printed return decodes near an integer
    best: list[tuple[int, float]] = []
    chunk = 20_000
    for start in range(0, len(p), chunk):
        sl = slice(start, start + chunk)
        z = alpha[sl, None] * Y[None, :] + beta[sl, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.where(z > 0, z, np.nan) ** (1 / p[sl, None])
        d = np.abs(q - np.round(q))
        score = np.nanmean(np.where(np.isfinite(d), d, 0.5), axis=1)
        good = np.flatnonzero(score < 0.2)
        best += [(start + int(i), float(score[i])) for i in good]
    best.sort(key=lambda t: t[1])
    fits = []
    for i, _ in best[:20]:
        fit = _refit(Y, alpha[i], beta[i], p[i], tol)
        if fit is not None:
            fits.append(fit)
    return fits


def _refit(Y: np.ndarray, alpha: float, beta: float, p0: float, tol: float) -> tuple[float, float, float, float] | None:
    """Round every decoded return to an integer and refit y = A n^p + B exactly; None unless all fit."""
    z = alpha * Y + beta
    if np.any(z <= 0):
        return None
    n = np.round(z ** (1 / p0))
    if np.any(n < 1) or np.any(np.diff(n) <= 0):
        return None

    def fit(lp: float) -> tuple[float, float, float]:
        x = n ** math.exp(lp)
        xm, ym = x.mean(), Y.mean()
        A = float(((x - xm) * (Y - ym)).sum() / ((x - xm) ** 2).sum())
        B = float(ym - A * xm)
        return float(np.max(np.abs(A * x + B - Y))), A, B

    a, b = math.log(p0) - 0.1, math.log(p0) + 0.1
    g = (math.sqrt(5) - 1) / 2
    for _ in range(50):  # golden-section search on the worst residual
        c1, c2 = b - g * (b - a), a + g * (b - a)
        if fit(c1)[0] < fit(c2)[0]:
            b = c2
        else:
            a = c1
    lp = (a + b) / 2
    resid, A, B = fit(lp)
    p = math.exp(lp)
    if A <= 0 or resid > 2.02 * tol + 1e-9 * float(np.max(np.abs(Y))):
        return None
    # chance that every non-reference return lands within the tolerance of an integer's image
    spacing = A * p * np.maximum(n, 1.0) ** (p - 1)
    chance = float(np.prod(np.minimum(1.0, 4 * tol / spacing[3:]))) if len(n) > 3 else 1.0
    s = float(_w(-B / A, 1 / p))  # B = -A w_p(s)
    return A, s, p, chance


# -- additivity --------------------------------------------------------------------------------
def additivity(v: View) -> Estimate:
    """(c, s, p) from: decoded return = sum of decoded components, with one map for all of them."""
    f = v.facts
    name = "additivity"
    if not f.components_sum_to_return:
        return Estimate(name, "c", None, "this task's components are not known to add up to the return")
    rows, anchors = [], []
    for e in v.entries:
        comps = {k: token_value(t) for k, t in e.components}
        if set(comps) != set(f.components) or any(x is None for x in comps.values()):
            continue
        rows.append((e.ret, [comps[k][0] for k in f.components]))  # type: ignore[index]
        if f.survive_component and f.time_limit and same_marker(e.diagnostics.get("termination"), "time_limit"):
            anchors.append(comps[f.survive_component][0])  # type: ignore[index]
    if len(rows) < 5:
        shown = sorted({k for e in v.entries for k, _ in e.components})
        why = f"components shown: {', '.join(shown) or 'none'}" if rows == [] else f"only {len(rows)} complete entries"
        return Estimate(name, "c", None, f"the return is not the sum of what is shown ({why})")
    R = np.array([r for r, _ in rows])
    C = np.array([c for _, c in rows])
    target = f.healthy_reward * f.time_limit if (anchors and f.healthy_reward and f.time_limit) else None
    S = 2000.0

    def residual(x: np.ndarray) -> float:
        lc, s, p = x
        c = math.exp(lc)
        if not (P_RANGE[0] <= p <= P_RANGE[1]):
            return math.inf
        ws = _w(s, p)
        dec = _w(C / c + ws, 1 / p)
        ret = _w(R / c + ws, 1 / p)
        err = np.abs(dec.sum(axis=1) - ret) / np.maximum(1.0, np.abs(ret))
        out = float(np.max(err))
        if target is not None:
            out = max(out, float(np.max(np.abs(_w(np.array(anchors) / c + ws, 1 / p) - target))) / target)
        return out

    best = min(((residual(np.array([lc, s, p])), (lc, s, p)) for lc in np.linspace(math.log(0.05), math.log(20), 25)
                for s in np.linspace(-S, S, 21) for p in np.exp(np.linspace(math.log(0.45), math.log(2.2), 25))),
               key=lambda t: t[0])
    x, val = _nelder_mead(residual, np.array(best[1]), np.array([0.2, 100.0, 0.1]))
    tol_rel = 1e-4
    if val > tol_rel:
        return Estimate(name, "c", None, f"no shared map makes the components add up (best relative misfit {val:.2g})")
    # identifiable? a c 30% off must not fit as well once s and p are refitted
    lc, s, p = x
    other, oval = _nelder_mead(lambda y: residual(np.array([lc + math.log(1.3), y[0], y[1]])), np.array([s, p]),
                               np.array([100.0, 0.1]))
    if oval <= tol_rel:
        return Estimate(name, "c", None, "the components add up under many maps (c is not determined)")
    return Estimate(name, "c", math.exp(lc), f"{len(rows)} entries add up under one map"
                    + (" (survive anchored at the time limit)" if target is not None else ""), extras={"s": s, "p": p})


def _nelder_mead(fun: Callable[[np.ndarray], float], x0: np.ndarray, step: np.ndarray, iters: int = 600) -> tuple[np.ndarray, float]:
    """A plain Nelder-Mead minimiser (no SciPy in the base install)."""
    pts = [x0] + [x0 + np.eye(len(x0))[i] * step[i] for i in range(len(x0))]
    vals = [fun(x) for x in pts]
    for _ in range(iters):
        order = np.argsort(vals)
        pts, vals = [pts[i] for i in order], [vals[i] for i in order]
        centroid = np.mean(pts[:-1], axis=0)
        xr = centroid + (centroid - pts[-1])
        fr = fun(xr)
        if fr < vals[0]:
            xe = centroid + 2 * (centroid - pts[-1])
            fe = fun(xe)
            pts[-1], vals[-1] = (xe, fe) if fe < fr else (xr, fr)
        elif fr < vals[-2]:
            pts[-1], vals[-1] = xr, fr
        else:
            xc = centroid + 0.5 * (pts[-1] - centroid)
            fc = fun(xc)
            if fc < vals[-1]:
                pts[-1], vals[-1] = xc, fc
            else:
                pts = [pts[0] + 0.5 * (x - pts[0]) for x in pts]
                vals = [fun(x) for x in pts]
    i = int(np.argmin(vals))
    return pts[i], float(vals[i])


# -- locomotion: survive and control cost ------------------------------------------------------
def _component(e_components: tuple[tuple[str, str], ...], key: str | None) -> float | None:
    if key is None:
        return None
    for k, t in e_components:
        if k == key:
            tv = token_value(t)
            return tv[0] if tv else None
    return None


def _steps(v: View, diagnostics: dict[str, str]) -> float | None:
    """Episode length: the diagnostic when shown, else the time limit when the episode reached it."""
    length = token_value(diagnostics.get("episode_length", ""))
    if length is not None and length[0] > 0:
        return length[0]
    if v.facts.time_limit and same_marker(diagnostics.get("termination"), "time_limit"):
        return float(v.facts.time_limit)
    return None


def survive_length(v: View) -> Estimate:
    """c = printed survive component / (healthy reward x episode length), constant over the entries."""
    f = v.facts
    if not f.survive_component or not f.healthy_reward:
        return Estimate("survive-length", "c", None, "no component with a public per-step value")
    ratios = []
    for e in v.entries:
        y, n = _component(e.components, f.survive_component), _steps(v, e.diagnostics)
        if y is not None and n is not None:
            healthy = n - 1 if same_marker(e.diagnostics.get("termination"), "unhealthy") else n  # the last step pays 0
            if healthy > 0:
                ratios.append(y / (f.healthy_reward * healthy))
    if not ratios:
        return Estimate("survive-length", "c", None, "the survive component or the episode length is not shown")
    med = float(np.median(ratios))
    if med <= 0 or (len(ratios) >= 2 and (max(ratios) - min(ratios)) > 0.001 * med):
        return Estimate("survive-length", "c", None, "printed survive / length is not constant")
    return Estimate("survive-length", "c", med, f"survive = {f.healthy_reward:g} x length on {len(ratios)} entries")


def saturated_ctrl(v: View) -> Estimate:
    """c from the most negative printed control cost per step, when several policies share it (saturation)."""
    f = v.facts
    if not f.ctrl_component or not f.ctrl_per_step:
        return Estimate("saturated-ctrl", "c", None, "no control cost with a public saturation value")
    per = []
    for e in v.entries:
        y, n = _component(e.components, f.ctrl_component), _steps(v, e.diagnostics)
        if y is not None and n is not None and y < 0:
            per.append((y / n, tuple(e.params)))
    if len(per) < 2:
        return Estimate("saturated-ctrl", "c", None, "the control cost or the episode length is not shown")
    low = min(r for r, _ in per)
    at = {p for r, p in per if r <= low * (1 - 1e-3)}
    if len(at) < 2:
        return Estimate("saturated-ctrl", "c", None, "no two policies share the lowest control cost per step")
    return Estimate("saturated-ctrl", "c", -low / f.ctrl_per_step,
                    f"{len(at)} policies at the saturated cost of {f.ctrl_per_step:g} per step")
