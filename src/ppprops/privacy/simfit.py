"""Simulator attacks: fit the secrets by simulating the task's public env (docs/threat-model.md).

The provider knows the encoded parameters it was shown (for its own proposals, the exact answers
it gave), the printed encoded returns, the diagnostics printed as they are, the public form of
every encoding (this code) and the public distribution of the secrets. When it can also build
the env, each hypothesis about the secrets is testable: decode the shown parameters with it, run
them, and compare the simulated raw returns, mapped by the best reward map for that hypothesis,
with the printed ones. Two attacks:

- ``sim-exact`` (premise: the episodes' initial states are known): from the run seed when the
  transcript gives it away (``runseed.find_run_seed``; episode seeds are
  ``seeding.episode_seeds(seed, index, 1)``), or when the env's ``reset`` does not depend on the
  seed. Every shown policy is simulated on its own initial state, so at the true secrets the fit
  reproduces every printed return to its printed precision.
- ``sim-marginal`` (no initial states): each shown policy is run on episodes drawn from the
  public initial-state distribution (seeds of the attacker's own), and the printed returns are
  fitted in expectation; raw diagnostics that the prompt still shows (CartPole's termination
  cause, Acrobot's mean tip height) are fitted the same way. For returns on a lattice (integer
  returns) under the warped, dithered map, ``sim-marginal-lattice`` reads the reward map of the
  hypothesis found a second way: the posterior median of an exact likelihood (``lattice_posterior``).

Both search the parameter secrets (a, and the offsets m under ``pp-hardened``) with CMA-ES inside
their public prior, and, for each hypothesis, solve the reward map (c; s and p when the prompt
says rewards are warped) in closed form on a grid of exponents. Both stop at a budget of
simulated steps (``SimLimits``: the same transcript gives the same fit whatever the machine's
load), or at a wall-clock cap when one is set, and report what they had by then. Each needs only
the ``View``.

Assumptions (public defaults the provider is taken to know): one episode per candidate (the
default ``episodes``), the warm-up first, one new candidate per iteration, and that a candidate
shown for the first time in iteration i's prompt is the one proposed in iteration i - 1.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import seeding
from ..client.codec import grid_scale
from ..client.secrets import HARDENED_A_LOG, HARDENED_P_LOG, LOG_HIGH, LOG_LOW
from ..wire.forms import CHAT, FORMS
from .simulator import Budget, OverBudget, Simulator, simulator_for
from .tokens import token_value
from .view import Estimate, RawGuess, View

ENCODED_LIMIT = 1.0e6  # the public clamp of warped encoded parameters (client.codec.ENCODED_LIMIT)
MARGINAL_EPISODES = 8  # episodes per shown policy in the marginal fit (attacker's own seeds)
LATTICE_EPISODES = 64  # episodes per shown policy for the marginal fit's final reward map on integer returns
MARGINAL_SEED = 20261201  # the attacker's own stream of reset seeds for the marginal fit
SEARCH_SEED = 7  # CMA-ES sampling stream (fixed: the attack is deterministic)
P_GRID = 17  # exponents tried per side of the hardened prior in the closed-form reward fit
POPSIZE = 16  # smallest CMA-ES population
STALL = 40  # CMA-ES generations without a 0.01% better fit before it counts as converged
MAX_RESTARTS = 6  # CMA-ES restarts (doubling the population) after a fit that does not reproduce the returns


@dataclass(frozen=True)
class SimLimits:
    """The budget of each simulator attack on one run, in simulated env steps (one step of one
    episode): at most ``vector_steps`` with a vectorised simulator (classic control), ``env_steps``
    with the real env. The step budget alone decides where a fit stops, so its result does not
    depend on the machine or its load.

    ``seconds``: an optional wall-clock cap per attack, in seconds (None, the default: none). A fit
    stopped by it depends on the machine's speed and load; it only keeps a slow env from running long.
    """

    vector_steps: int = 10_000_000
    env_steps: int = 100_000
    seconds: float | None = None

    def budget(self, kind: str) -> Budget:
        """A fresh Budget for a simulator of ``kind`` ("vector" or "env")."""
        return Budget(self.vector_steps if kind == "vector" else self.env_steps, self.seconds)

    def describe(self) -> str:
        """The bound in words, for the audit's output."""
        cap = f", and at most {self.seconds:g} s of wall clock" if self.seconds is not None else ""
        return (f"{self.vector_steps:.3g} simulated steps (vectorised classic control) or {self.env_steps:.3g} steps of the "
                f"real env{cap}, per attack")


DEFAULT_LIMITS = SimLimits()


# -- what the prompt says about the encodings ------------------------------------------------------
@dataclass(frozen=True)
class Scheme:
    """The public form of the encodings: ``params`` scale | affine | warp, ``rewards`` scale |
    affine | warp, and ``dither``: the public step of a return that the codec dithers (0: none)."""

    params: str
    rewards: str
    dither: float = 0.0

    @property
    def hardened(self) -> bool:
        """True for offsets or warps (pp-hardened's switches)."""
        return self.params != "scale" or self.rewards != "scale"


_PARAM_WORDS = (("warp", "increasing transformation of its own"), ("affine", "shifted by an offset"),
                ("scale", "multiplied by a positive factor of its own"))
_REWARD_WORDS = (("warp", "pass through increasing transformations"), ("affine", "shifted and multiplied"),
                 ("scale", "multiplied by one positive constant"))


def schemes_of(v: View) -> list[Scheme]:
    """The encodings the prompt describes (chat form); the document form says nothing, so both
    presets are tried (``pp`` and ``pp-hardened``), the better fit wins. Empty when the prompt
    shows raw parameters or raw returns (nothing to fit)."""
    text = v.requests[0].text if v.requests else ""
    step = (v.facts.resolution or {}).get("return", 0.0)
    params = next((k for k, w in _PARAM_WORDS if w in text), None)
    rewards = next((k for k, w in _REWARD_WORDS if w in text), None)
    if params and rewards:
        return [Scheme(params, rewards, step if rewards == "warp" else 0.0)]
    form = FORMS.get(v.requests[0].form) if v.requests else None
    if form is not None and not form.describes_encoding and form.entries(text) and "encoded" not in text:
        return [Scheme("scale", "scale"), Scheme("warp", "warp", step)]
    return []


# -- the shown history as data -------------------------------------------------------------------
@dataclass
class Data:
    """The shown entries an attack fits: ``E`` encoded parameters (n, D), the provider's own
    answer where it matches the shown entry, else as printed (or replayed: the encoded warm-up);
    ``raw`` raw parameters known outright (the replayed raw warm-up of ``pp``; NaN otherwise);
    ``y``/``tol`` printed encoded returns and their precision; ``index`` the candidate index
    (-1 unknown); ``num``/``cat`` the diagnostics printed, numeric (NaN missing) or text."""

    E: NDArray[np.float64]
    raw: NDArray[np.float64]
    y: NDArray[np.float64]
    tol: NDArray[np.float64]
    index: NDArray[np.int64]
    num: dict[str, NDArray[np.float64]]
    cat: dict[str, NDArray[Any]]
    entries: list[int]  # positions in View.entries


def _answers(v: View) -> dict[int, NDArray[np.float64]]:
    """iteration -> the vector of the provider's last usable answer in that iteration."""
    out: dict[int, NDArray[np.float64]] = {}
    for r in v.requests:
        res = FORMS.get(r.form, CHAT).read(r.answer, v.D)
        if res.values is not None:
            out[r.iteration] = np.array(res.values, dtype=np.float64)
    return out


_TOPK = re.compile(r"at most the (\d+) best")


def observed(v: View, replay: dict[int, int] | None = None, raw_warmup: NDArray[np.float64] | None = None,
             enc_warmup: NDArray[np.float64] | None = None) -> Data:
    """The shown entries as arrays (see ``Data``). ``replay`` maps a warm-up entry (position in
    ``View.entries``) to its warm-up draw index when the run seed is known; ``raw_warmup`` /
    ``enc_warmup`` are those draws (raw for ``pp``, encoded for an encoded warm-up)."""
    answers = _answers(v)
    first = len(v.warmup)
    m = _TOPK.search(v.requests[0].text) if v.requests else None
    k_shown = int(m.group(1)) if m else None
    n_warm: int | None = first if (k_shown is None or first < k_shown) else None
    if replay and n_warm is not None and max(replay.values()) >= n_warm:
        n_warm = None
    if n_warm is None and replay and k_shown is not None and first == k_shown and max(replay.values()) < first:
        n_warm = first  # every shown warm-up draw is among the first K: the K shown are all of them
    warm_ids = {id(e) for e in v.warmup}
    E, raw, y, tol, idx, keep = [], [], [], [], [], []
    for pos, e in enumerate(v.entries):
        params = np.array(e.params, dtype=np.float64)
        r = np.full(v.D, np.nan)
        index = -1
        if id(e) in warm_ids:
            if replay is not None and pos in replay:
                index = replay[pos]
                if enc_warmup is not None:
                    params = enc_warmup[index].copy()
                if raw_warmup is not None:
                    r = raw_warmup[index].copy()
        else:
            it = v.requests[e.first_call].iteration
            if n_warm is not None and it >= 1:
                index = n_warm + it - 1
            ans = answers.get(it - 1)
            if ans is not None and np.all(np.abs(ans - params) <= np.asarray(e.tols) * (1 + 1e-9) + 1e-12):
                params = ans  # the provider knows its own answer to full precision
        E.append(params)
        raw.append(r)
        y.append(e.ret)
        tol.append(e.ret_tol)
        idx.append(index)
        keep.append(pos)
    names = sorted({k for e in v.entries for k in e.diagnostics})
    num: dict[str, NDArray[np.float64]] = {}
    cat: dict[str, NDArray[Any]] = {}
    for k in names:
        vals = [v.entries[p].diagnostics.get(k) for p in keep]
        parsed = [token_value(x) if x is not None else None for x in vals]
        if all(p is not None for p in parsed if p is not None) and any(p is not None for p in parsed) and \
                all(x is None or p is not None for x, p in zip(vals, parsed, strict=True)):
            num[k] = np.array([p[0] if p is not None else np.nan for p in parsed])
        else:
            cat[k] = np.array(vals, dtype=object)
    return Data(np.array(E).reshape(len(E), v.D), np.array(raw).reshape(len(raw), v.D), np.array(y), np.array(tol),
                np.array(idx, dtype=np.int64), num, cat, keep)


# -- initial states ---------------------------------------------------------------------------------
def known_seeds(v: View, sim: Simulator) -> tuple[Data | None, NDArray[np.int64] | None, str]:
    """(data, one reset seed per entry, how) when the initial states are known to the attacker:
    the env's reset ignores its seed, or the run seed was read off the transcript (then the
    entries whose candidate index is known). (None, None, why) otherwise."""
    from .runseed import find_run_seed, replay_warmup

    if _reset_ignores_seed(sim):
        d = observed(v)
        return d, np.zeros(len(d.y), dtype=np.int64), "the env's initial state does not depend on the reset seed"
    seed, how = find_run_seed(v)
    if seed is None:
        return None, None, f"initial states unknown (the run seed is not in the transcript: {how})"
    replay, raw_w, enc_w = replay_warmup(v, seed)
    d = observed(v, replay, raw_w, enc_w)
    known = d.index >= 0
    if known.sum() < 2:
        return None, None, f"initial states unknown for the shown entries ({how}, but their candidate indices are not)"
    d = _subset(d, known)
    seeds = np.array([seeding.episode_seeds(seed, int(i), 1)[0] for i in d.index], dtype=np.int64)
    return d, seeds, f"initial states from the run seed ({how})"


def _subset(d: Data, keep: NDArray[np.bool_]) -> Data:
    return Data(d.E[keep], d.raw[keep], d.y[keep], d.tol[keep], d.index[keep], {k: x[keep] for k, x in d.num.items()},
                {k: x[keep] for k, x in d.cat.items()}, [p for p, k in zip(d.entries, keep, strict=True) if k])


def _reset_ignores_seed(sim: Simulator) -> bool:
    init = getattr(sim, "initial_state", None)
    if init is not None:
        a, b, c = init(1), init(2), init(12345)
        return bool(np.array_equal(a, b) and np.array_equal(a, c))
    env = sim._make() if hasattr(sim, "_make") else None  # EnvSim
    if env is None:
        return False
    obs = [np.asarray(env.reset(seed=s)[0], dtype=np.float64).ravel() for s in (1, 2, 12345)]
    return all(np.array_equal(obs[0], o) for o in obs[1:])


# -- the decode maps (client.codec, public) ----------------------------------------------------------
def _t(theta: NDArray[np.float64], lo: float, hi: float) -> NDArray[np.float64]:
    w = hi - lo
    u = (np.clip(theta, lo, hi) - lo) / w
    with np.errstate(over="ignore", invalid="ignore"):
        return (w / math.pi) * np.tan(math.pi * (u - 0.5))


def _t_inv(z: NDArray[np.float64], lo: float, hi: float) -> NDArray[np.float64]:
    w = hi - lo
    return lo + w * (0.5 + np.arctan(math.pi * z / w) / math.pi)


@dataclass(frozen=True)
class Space:
    """The search space of the parameter secrets: z = (ln a_1..D[, m_1..D]) within the public prior."""

    scheme: Scheme
    D: int
    box: tuple[float, float]
    grid: bool = False  # the transcript is on the grid: a_j is the effective g a_j, g in [G/2, G] (client.codec)

    @property
    def offsets(self) -> bool:
        """True when the parameters have secret origins m (affine or warped encodings)."""
        return self.scheme.params in ("affine", "warp")

    @property
    def dim(self) -> int:
        """Dimensions of z."""
        return 2 * self.D if self.offsets else self.D

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The prior's support: ln a_j within the scheme's range; m_j within the central half of the box."""
        la = HARDENED_A_LOG if self.scheme.params == "warp" else (LOG_LOW, LOG_HIGH)
        if self.grid:  # the secret grid factor g = G u, u in [1/2, 1], widens the support of the effective scale
            G = grid_scale(self.box, self.scheme.params == "warp")
            la = (la[0] + math.log(G / 2), la[1] + math.log(G))
        lo, hi = self.box
        mid, quarter = (lo + hi) / 2, (hi - lo) / 4
        low = [la[0]] * self.D + ([mid - quarter] * self.D if self.offsets else [])
        high = [la[1]] * self.D + ([mid + quarter] * self.D if self.offsets else [])
        return np.array(low), np.array(high)

    def decode(self, Z: NDArray[np.float64], E: NDArray[np.float64]) -> NDArray[np.float64]:
        """Raw parameters of every entry under every hypothesis: Z (H, dim), E (n, D) -> (H, n, D)."""
        a = np.exp(Z[:, : self.D])[:, None, :]
        lo, hi = self.box
        if self.scheme.params == "warp":
            m = Z[:, self.D:][:, None, :]
            return _t_inv(np.clip(E[None], -ENCODED_LIMIT, ENCODED_LIMIT) / a + _t(m, lo, hi), lo, hi)
        shift = Z[:, self.D:][:, None, :] if self.offsets else np.zeros((1, 1, self.D))
        return np.clip(E[None] / a + shift, lo, hi)


# -- the reward map, in closed form -------------------------------------------------------------------
def _w(x: NDArray[np.float64] | float, p: NDArray[np.float64] | float) -> Any:
    return np.sign(x) * np.abs(x) ** p


def _p_grid(scheme: Scheme) -> list[float]:
    if scheme.rewards != "warp":
        return [1.0]
    side = np.exp(np.linspace(HARDENED_P_LOG[0], HARDENED_P_LOG[1], P_GRID))
    return sorted([*side.tolist(), *(1 / side).tolist()])


@dataclass(frozen=True)
class RewardFit:
    """Best reward map per hypothesis: ``misfit`` (H,) the RMS residual over the printed spread,
    ``rms`` (H,) the RMS residual in printed units, and ``c``, ``s``, ``p`` (H,) each."""

    misfit: NDArray[np.float64]
    rms: NDArray[np.float64]
    c: NDArray[np.float64]
    s: NDArray[np.float64]
    p: NDArray[np.float64]


@dataclass(frozen=True)
class RewardPrior:
    """The public support of the reward secrets: c in [c_lo, c_hi]; |s| <= S (the task's public
    reward scale, ``client.hardening.reward_scale``)."""

    c_lo: float = math.exp(LOG_LOW)
    c_hi: float = math.exp(LOG_HIGH)
    S: float = 1000.0


def _spread(y: NDArray[np.float64], scheme: Scheme) -> float:
    """The printed returns' spread, the unit of the misfit (the same for every scheme, so fits compare)."""
    sd = float(np.std(y))
    return (sd if sd > 0 else float(np.sqrt(np.mean(y**2)))) + 1e-12


def _fit_p(X: NDArray[np.float64], y: NDArray[np.float64], p: NDArray[np.float64], scheme: Scheme,
           prior: RewardPrior) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Least squares of y ~ c (X - w_p(s)) per row of ``X`` (H, n), within the prior's support:
    the unconstrained solution when it lies inside, else the best one on its boundary (c or s at a
    bound). Returns (rms, c, s), each (H,)."""
    H = len(X)
    ym = y.mean()

    def slope_only(Xs: NDArray[np.float64]) -> NDArray[np.float64]:  # c for a given intercept shift
        return np.clip(np.sum(Xs * y, axis=1) / np.maximum(np.sum(Xs * Xs, axis=1), 1e-300), prior.c_lo, prior.c_hi)

    def rms_of(c: NDArray[np.float64], beta: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.sqrt(np.mean((y[None, :] - c[:, None] * X - beta[:, None]) ** 2, axis=1))

    if scheme.rewards == "scale":
        c = slope_only(X)
        return rms_of(c, np.zeros(H)), c, np.zeros(H)
    xm = X.mean(axis=1)
    xc = X - xm[:, None]
    c0 = np.sum(xc * (y - ym), axis=1) / np.maximum(np.sum(xc * xc, axis=1), 1e-300)
    options = []
    for c in (np.clip(c0, prior.c_lo, prior.c_hi),):
        beta = ym - c * xm
        s = _w(-beta / c, 1.0 / p)
        inside = np.abs(s) <= prior.S
        options.append((np.where(inside, rms_of(c, beta), np.inf), c, s))
    wS = prior.S ** p
    for sign in (-1.0, 1.0):  # s on the boundary: y = c (X - w_p(+-S)), c free within its support
        shift = sign * wS
        c = slope_only(X - shift[:, None])
        options.append((rms_of(c, -c * shift), c, np.full(H, sign * prior.S)))
    rms = np.array([o[0] for o in options])
    k = np.argmin(rms, axis=0)
    pick = np.arange(H)
    return rms[k, pick], np.array([o[1] for o in options])[k, pick], np.array([o[2] for o in options])[k, pick]


def fit_rewards(R: NDArray[np.float64], y: NDArray[np.float64], scheme: Scheme, prior: RewardPrior | None = None,
                ps: list[float] | None = None, refine: int = 8) -> RewardFit:
    """The reward map y ~ c (mean_e w_p(R) - w_p(s)) of each hypothesis, within the prior's support.

    ``R`` (H, n, E): simulated raw returns of the n entries, E episodes each; ``y`` (n,) printed
    returns. Under a pure scale s = 0 and p = 1; under a warp p is searched on a grid of the
    prior's support (both sides of 1), then refined per hypothesis by ``refine`` golden-section
    steps on ln p.
    """
    prior = prior or RewardPrior()
    H = R.shape[0]
    spread = _spread(y, scheme)
    grid = np.asarray(ps if ps is not None else _p_grid(scheme), dtype=np.float64)
    sign, logabs = np.sign(R), np.log(np.maximum(np.abs(R), 1e-300))

    def at(p: NDArray[np.float64], rows: NDArray[np.intp]) -> tuple[NDArray[np.float64], ...]:
        if scheme.rewards == "warp":
            X = np.mean(sign[rows] * np.exp(p[:, None, None] * logabs[rows]), axis=2)
        else:
            X = np.mean(R[rows], axis=2)
        return _fit_p(X, y, p, scheme, prior)

    G = len(grid)
    rows = np.tile(np.arange(H), G)
    r_all, c_all, s_all = at(np.repeat(grid, H), rows)
    r_all, c_all, s_all = r_all.reshape(G, H), c_all.reshape(G, H), s_all.reshape(G, H)
    k = np.argmin(r_all, axis=0)
    cols = np.arange(H)
    rms, c, s, p = r_all[k, cols], c_all[k, cols], s_all[k, cols], grid[k]
    if scheme.rewards == "warp" and refine and G > 2:
        lg = np.log(grid)
        lo, hi = lg[np.maximum(k - 1, 0)], lg[np.minimum(k + 1, G - 1)]
        g = (math.sqrt(5) - 1) / 2
        both = np.concatenate([cols, cols])
        for _ in range(refine):
            a1, a2 = hi - g * (hi - lo), lo + g * (hi - lo)
            f = at(np.exp(np.concatenate([a1, a2])), both)[0]
            left = f[:H] < f[H:]
            hi, lo = np.where(left, a2, hi), np.where(left, lo, a1)
        pm = np.exp((lo + hi) / 2)
        r2, c2, s2 = at(pm, cols)
        better = r2 < rms
        rms, c, s, p = np.where(better, r2, rms), np.where(better, c2, c), np.where(better, s2, s), np.where(better, pm, p)
    ok = np.isfinite(rms) & (c > 0)
    return RewardFit(np.where(ok, rms / spread, np.inf), np.where(ok, rms, np.inf), c, s, p)


# -- the search -----------------------------------------------------------------------------------------
@dataclass
class Fit:
    """The best hypothesis found: the secrets it implies, the raw values it decodes, how well it fits."""

    scheme: Scheme
    a: NDArray[np.float64]
    m: NDArray[np.float64] | None
    c: float
    s: float
    p: float
    misfit: float  # reward misfit (RMS residual / printed spread) plus diagnostic misfits
    rms: float  # RMS residual of the printed returns, in printed units
    raw_params: NDArray[np.float64]  # (n, D)
    raw_returns: NDArray[np.float64]  # (n,) simulated (exact) or expected (marginal)
    exact: bool  # every printed return reproduced within its printed precision (and the dither)
    steps: int
    entries: list[int] = field(default_factory=list)  # the View.entries position of each fitted row
    stopped: str = ""  # why the search stopped early ("over its budget ...")
    notes: list[str] = field(default_factory=list)
    lattice: tuple[float, float, float] | None = None  # (c, s, p) by ``lattice_posterior`` (marginal fit, lattice returns)


Objective = Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], RewardFit, NDArray[np.float64]]]


def _objective(space: Space, d: Data, sim: Simulator, seeds: NDArray[np.int64], episodes: int,
               prior: RewardPrior, trace: list[tuple[NDArray[np.float64], NDArray[np.float64], RewardFit]] | None = None) -> Objective:
    """Loss of each hypothesis (rows of Z); returns (loss, reward fit, raw returns (H, n, E)).

    With known initial states (``episodes`` 1, exact): the reward misfit plus the misfit of every
    raw diagnostic the simulator reproduces. Over the public initial-state distribution
    (``episodes`` > 1): a negative log-likelihood, Gaussian in the printed returns (profile
    variance) and in numeric diagnostics, and the simulated frequency of each printed text
    diagnostic; every hypothesis evaluated is appended to ``trace`` as (z, loss, reward fit).
    """
    n = len(d.y)
    marginal = episodes > 1
    floor = float(np.mean(d.tol)) ** 2

    def run(Z: NDArray[np.float64]) -> tuple[NDArray[np.float64], RewardFit, NDArray[np.float64]]:
        H = len(Z)
        theta = space.decode(Z, d.E)
        known = np.isfinite(d.raw).all(axis=1)
        if known.any():
            theta[:, known, :] = d.raw[known][None]
        th = np.repeat(theta.reshape(H * n, -1), episodes, axis=0)
        sd = np.tile(seeds.reshape(n, episodes), (H, 1)).reshape(-1)
        out = sim.rollout(th, sd.tolist())
        R = out.returns.reshape(H, n, episodes)
        fit = fit_rewards(R, d.y, space.scheme, prior)
        loss = 0.5 * n * np.log(fit.rms**2 + floor) if marginal else fit.misfit.copy()
        for name, printed in d.num.items():
            if name not in out.diagnostics or out.diagnostics[name].dtype == object:
                continue
            sim_v = out.diagnostics[name].astype(np.float64).reshape(H, n, episodes).mean(axis=2)
            ok = np.isfinite(printed)
            if ok.sum() < 2:
                continue
            msq = np.mean((sim_v[:, ok] - printed[ok]) ** 2, axis=1)
            if marginal:
                loss = loss + 0.5 * ok.sum() * np.log(msq + 1e-6)
            else:
                loss = loss + np.sqrt(msq) / (float(np.std(printed[ok])) + 1e-3)
        for name, printed in d.cat.items():
            if name not in out.diagnostics or out.diagnostics[name].dtype != object:
                continue
            sim_c = out.diagnostics[name].reshape(H, n, episodes)
            ok = np.array([x is not None for x in printed])
            if not ok.any():
                continue
            hits = np.sum(sim_c == printed[None, :, None], axis=2)  # episodes that end as printed
            if marginal:
                loss = loss - np.sum(np.log((hits[:, ok] + 0.5) / (episodes + 1.0)), axis=1)
            else:
                loss = loss + np.mean(1.0 - hits[:, ok] / episodes, axis=1)
        loss = np.where(np.isfinite(fit.rms), loss, np.inf)
        if trace is not None:
            trace.append((Z.copy(), loss.copy(), fit))
        return loss, fit, R

    return run


def _cma(run: Objective, space: Space, x0: NDArray[np.float64], sigma0: float, *, popsize: int,
         rng: np.random.Generator, max_gens: int = 400) -> tuple[NDArray[np.float64], float, str]:
    """CMA-ES (Hansen's defaults, clipped to the prior's support) from ``x0`` until it converges;
    returns the best z, its loss, and why it stopped early ("" converged, else the budget's words)."""
    low, high = space.bounds()
    scale = high - low
    n = len(x0)
    lam = popsize
    mu = lam // 2
    w = np.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w /= w.sum()
    mueff = 1.0 / np.sum(w**2)
    cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
    cs = (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chin = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
    mean = (x0 - low) / scale  # search in the prior box normalised to [0, 1]
    sigma = sigma0
    C = np.eye(n)
    pc = np.zeros(n)
    ps = np.zeros(n)
    best_z, best_f = x0.copy(), math.inf
    stall = 0
    for _ in range(max_gens):
        vals, B = np.linalg.eigh(C)
        Dm = np.sqrt(np.maximum(vals, 1e-20))
        noise = rng.standard_normal((lam, n))
        Y = noise * Dm @ B.T
        X = np.clip(mean + sigma * Y, 0.0, 1.0)
        try:
            f, _, _ = run(low + X * scale)
        except OverBudget as e:
            return best_z, best_f, e.what
        f = np.where(np.isfinite(f), f, np.inf)
        order = np.argsort(f, kind="stable")
        if f[order[0]] < best_f:
            stall = 0 if not math.isfinite(best_f) or f[order[0]] < best_f * (1 - 1e-4) else stall + 1
            best_f, best_z = float(f[order[0]]), low + X[order[0]] * scale
        else:
            stall += 1
        Ysel = (X[order[:mu]] - mean) / sigma
        old = mean
        mean = mean + sigma * (w @ Ysel)
        y = (mean - old) / sigma
        invsqrt = B @ np.diag(1 / Dm) @ B.T
        ps = (1 - cs) * ps + math.sqrt(cs * (2 - cs) * mueff) * (invsqrt @ y)
        hsig = np.linalg.norm(ps) / math.sqrt(1 - (1 - cs) ** 2) / chin < 1.4 + 2 / (n + 1)
        pc = (1 - cc) * pc + hsig * math.sqrt(cc * (2 - cc) * mueff) * y
        C = ((1 - c1 - cmu) * C + c1 * (np.outer(pc, pc) + (not hsig) * cc * (2 - cc) * C)
             + cmu * (Ysel.T * w) @ Ysel)
        C = (C + C.T) / 2
        sigma *= math.exp((cs / damps) * (np.linalg.norm(ps) / chin - 1))
        if sigma * math.sqrt(float(np.max(vals))) < 1e-7 or stall > STALL or not math.isfinite(sigma):
            break
    return best_z, best_f, ""


def search(v: View, d: Data, sim: Simulator, seeds: NDArray[np.int64], episodes: int, schemes: list[Scheme],
           *, exact: bool, prior: RewardPrior) -> Fit:
    """Fit the secrets to ``d`` by simulation (see the module docstring). ``seeds``: (n * episodes,)
    reset seeds, entry by entry; ``prior`` the public support of the reward secrets. Raises
    OverBudget when not even one hypothesis could be simulated."""
    rng = np.random.default_rng(SEARCH_SEED)
    best: tuple[float, Space, NDArray[np.float64]] | None = None
    stopped = ""
    traces: dict[Scheme, list[tuple[NDArray[np.float64], NDArray[np.float64], RewardFit]]] = {}
    total = sim.budget.steps
    for k, scheme in enumerate(schemes):  # the budget is shared out between the schemes tried
        sim.budget.steps = sim.budget.used + (total - sim.budget.used) // (len(schemes) - k)
        space = Space(scheme, v.D, v.box, grid=v.grid)
        trace = traces.setdefault(scheme, []) if not exact else None
        run = _objective(space, d, sim, seeds, episodes, prior, trace)
        low, high = space.bounds()
        fixed = scheme.params == "scale" and np.isfinite(d.raw).all(axis=1).sum() >= 1 and _scale_from_raw(d) is not None
        target = _exact_level(d, scheme)

        def good(f: float, target: float = target) -> bool:
            return exact and f <= target

        cand: tuple[float, Space, NDArray[np.float64]] | None = None
        if fixed:  # pp with the raw warm-up replayed: a follows outright, only the reward map is left
            z0 = np.log(_scale_from_raw(d))  # type: ignore[arg-type]
            f0, _, _ = run(z0[None])
            cand = (float(f0[0]), space, z0)
        else:
            x0, sigma = _start(v, space), 0.3
            pop = max(POPSIZE, 4 + int(3 * math.log(space.dim)) * 2)
            for attempt in range(MAX_RESTARTS + 1):
                z, f, why = _cma(run, space, x0, sigma, popsize=pop, rng=rng, max_gens=400 if sigma > 0.1 else 60)
                improved = cand is None or f < cand[0] * (1 - 1e-3)
                if cand is None or f < cand[0]:
                    cand = (f, space, z)
                if why:
                    stopped = why if k == len(schemes) - 1 else ""
                    break
                if good(f):
                    break
                if improved and attempt < MAX_RESTARTS:  # converged somewhere new: look closer around the best first
                    x0, sigma = cand[2], 0.05
                else:  # nothing better nearby: elsewhere, with a larger population
                    pop *= 2
                    x0, sigma = low + rng.uniform(size=space.dim) * (high - low), 0.4
        if cand is not None and math.isfinite(cand[0]) and (best is None or cand[0] < best[0]):
            best = cand
    sim.budget.steps = total
    if best is None:
        raise OverBudget(stopped or "no hypothesis could be simulated")
    f_best, space, z_best = best
    averaged = _posterior_mean(traces.get(space.scheme, []), space) if not exact else None
    return _finish(v, d, sim, seeds, episodes, space, z_best if averaged is None else averaged[0], f_best, exact, stopped, prior,
                   None if averaged is None else averaged[1])


def _posterior_mean(trace: list[tuple[NDArray[np.float64], NDArray[np.float64], RewardFit]],
                    space: Space) -> tuple[NDArray[np.float64], tuple[float, float, float]] | None:
    """The likelihood-weighted mean of every hypothesis the search evaluated (weights exp(-loss),
    the loss a negative log-likelihood): z, and (ln c, s, ln p) averaged, so the estimate does not
    hinge on the single best of many noisy fits."""
    if not trace:
        return None
    Z = np.concatenate([t[0] for t in trace])
    L = np.concatenate([t[1] for t in trace])
    c = np.concatenate([t[2].c for t in trace])
    s = np.concatenate([t[2].s for t in trace])
    p = np.concatenate([t[2].p for t in trace])
    ok = np.isfinite(L) & (c > 0) & (p > 0)
    if not ok.any():
        return None
    w = np.exp(-(L[ok] - L[ok].min()))
    w /= w.sum()
    z = w @ Z[ok]
    return z, (float(np.exp(w @ np.log(c[ok]))), float(w @ s[ok]), float(np.exp(w @ np.log(p[ok]))))


def _scale_from_raw(d: Data) -> NDArray[np.float64] | None:
    """a_j from entries whose raw parameters are known (encoded / raw, least squares)."""
    known = np.isfinite(d.raw).all(axis=1)
    if not known.any():
        return None
    X, E = d.raw[known], d.E[known]
    num, den = np.sum(X * E, axis=0), np.sum(X * X, axis=0)
    a = num / np.maximum(den, 1e-300)
    return a if np.all(a > 0) else None


def _start(v: View, space: Space) -> NDArray[np.float64]:
    """The search's first mean: the prior's centre, or under a pure scale the warm-up's range estimate."""
    low, high = space.bounds()
    x0 = (low + high) / 2
    if space.scheme.params == "scale" and len(v.warmup) >= 2:
        X = np.array([e.params for e in v.warmup])
        a = np.max(np.abs(X), axis=0) * (len(X) + 1) / len(X) / max(abs(v.box[0]), abs(v.box[1]))
        x0[: space.D] = np.clip(np.log(np.maximum(a, 1e-6)), low[: space.D], high[: space.D])
    return x0


def _exact_level(d: Data, scheme: Scheme) -> float:
    """The loss at which a fit reproduces every printed return within its precision (no diagnostic misfit)."""
    spread = _spread(d.y, scheme)
    slack = 2.0 * float(np.max(d.tol))
    if scheme.dither:
        slack += 0.05 * spread  # the dither: within half a step of the return grid, distorted by the warp
    return slack / spread


def lattice_posterior(R: NDArray[np.float64], y: NDArray[np.float64], step: float, prior: RewardPrior) -> tuple[float, float, float]:
    """(c, s, p): the posterior medians of the warped, dithered reward map of returns on a lattice.

    The codec prints y = c (w_p(r + d) - w_p(s)) with r on the lattice of ``step`` (integer returns:
    1) and d uniform on +-step/2 (``client.codec``). Under a hypothesis (c, s, p) each printed
    return therefore names one raw return, x = w_p^-1(y / c + w_p(s)) rounded to the lattice, with
    density P(r = round(x)) / (c p |x|^(p-1)) (the warp's Jacobian; d contributes 1 / step). P comes
    from ``R`` (n, E): E simulated episodes of each of the n shown policies (counts smoothed over
    the neighbouring lattice points, plus a floor). The posterior over a grid flat in ln p (each
    side of 1, the public support), s (on +-S) and ln c (the public support) gives each secret's
    median (closer than the maximum in the measurements of docs/threat-model.md, where the
    likelihood pins c loosely). About 82 x 201 x 301 x n evaluations: seconds for tens of entries.
    The grid bounds the precision: p moves in steps of 1.2%, so when the raw returns are pinned
    and |r| is near 500, the grid rather than the data limits c to about 10%.
    """
    n = len(y)
    side = np.linspace(HARDENED_P_LOG[0], HARDENED_P_LOG[1], 41)
    ps = np.exp(np.concatenate([-side[::-1], side]))
    ss = np.linspace(-prior.S, prior.S, 201)
    cs = np.exp(np.linspace(math.log(prior.c_lo), math.log(prior.c_hi), 301))
    k_sim = np.rint(R / step).astype(np.int64)
    lo, hi = int(k_sim.min()) - 2, int(k_sim.max()) + 2
    counts = np.zeros((n, hi - lo + 1))
    for i in range(n):
        np.add.at(counts[i], k_sim[i] - lo, 1.0)
    smooth = np.array([np.convolve(row, [0.25, 0.5, 0.25], mode="same") for row in counts]) + 0.02
    logpmf = np.log(smooth / smooth.sum(axis=1, keepdims=True))
    rows = np.arange(n)[None, None, :]
    LL = np.empty((len(ps), len(ss), len(cs)))
    for i, p in enumerate(ps):  # (s, c, entry) at once for each exponent
        x = _w(y[None, None, :] / cs[None, :, None] + _w(ss, p)[:, None, None], 1.0 / p)
        k = np.rint(x / step).astype(np.int64)
        inside = (k >= lo) & (k <= hi)
        ll = (logpmf[rows, np.clip(k - lo, 0, hi - lo)] - np.log(cs[None, :, None] * p / step)
              - (p - 1) * np.log(np.maximum(np.abs(x), 1e-9)))
        LL[i] = np.where(inside, ll, -1e9).sum(axis=2)
    w = np.exp(LL - LL.max())
    w /= w.sum()

    def median(grid: NDArray[np.float64], mass: NDArray[np.float64]) -> float:
        return float(grid[min(int(np.searchsorted(np.cumsum(mass), 0.5)), len(grid) - 1)])

    return median(cs, w.sum(axis=(0, 1))), median(ss, w.sum(axis=(0, 2))), median(ps, w.sum(axis=(1, 2)))


def _finish(v: View, d: Data, sim: Simulator, seeds: NDArray[np.int64], episodes: int, space: Space, z: NDArray[np.float64],
            f: float, exact: bool, stopped: str, prior: RewardPrior, reward: tuple[float, float, float] | None = None) -> Fit:
    """The secrets and raw values of hypothesis ``z``, with the exponent refined further (or the
    reward map ``reward`` = (c, s, p) when given: the marginal fit's average). For returns on a
    lattice under a warped, dithered map the marginal fit also gives ``Fit.lattice``: the
    posterior medians of ``lattice_posterior`` on ``LATTICE_EPISODES`` episodes of each decoded
    policy (a second estimate of the same hypothesis; neither is always the closer)."""
    theta = space.decode(z[None], d.E)
    known = np.isfinite(d.raw).all(axis=1)
    if known.any():
        theta[:, known, :] = d.raw[known][None]
    sim.budget.steps += len(seeds) * 100_000  # the final decoding is always simulated, past the budget if need be
    sim.budget.seconds = None
    out = sim.rollout(np.repeat(theta[0], episodes, axis=0), seeds.tolist())
    R = out.returns.reshape(1, len(d.y), episodes)
    fit = fit_rewards(R, d.y, space.scheme, prior, refine=40)
    lattice = None
    if not exact and space.scheme.rewards == "warp" and space.scheme.dither > 0:  # the likelihood reads each raw return
        draws = np.random.default_rng(MARGINAL_SEED + 1).integers(0, 2**31, size=LATTICE_EPISODES)
        sim.budget.steps += len(d.y) * LATTICE_EPISODES * 100_000
        many = sim.rollout(np.repeat(theta[0], LATTICE_EPISODES, axis=0), np.tile(draws, len(d.y)).tolist())
        lattice = lattice_posterior(many.returns.reshape(len(d.y), LATTICE_EPISODES), d.y, space.scheme.dither, prior)
    a = np.exp(z[: v.D])
    replayed = _scale_from_raw(d) if space.scheme.params == "scale" else None
    if replayed is not None:
        a = replayed
    m = z[v.D:] if space.offsets else None
    c, s, p = (float(fit.c[0]), float(fit.s[0]), float(fit.p[0])) if reward is None else reward
    reproduced = exact and _reproduces(d, out, R[0, :, 0], c, s, p, space.scheme)
    return Fit(space.scheme, a, m, c, s, p, f, float(fit.rms[0]), theta[0], R[0].mean(axis=1), reproduced,
               sim.budget.used, list(d.entries), stopped, lattice=lattice)


def _reproduces(d: Data, out: Any, R: NDArray[np.float64], c: float, s: float, p: float, scheme: Scheme) -> bool:
    """Every printed return within its precision of c (w_p(R) - w_p(s)), widened by the largest
    effect of the dither (half a step of the return grid through the warp's slope), and every
    printed diagnostic the simulator also produces equal to the simulated one."""
    pred = c * (_w(R, p) - _w(s, p)) if scheme.rewards != "scale" else c * R
    slack = 2.0 * d.tol + 1e-9 * np.abs(d.y)  # the least-squares map may miss a printed return by more than its rounding
    if scheme.dither:
        slack = slack + 0.5 * scheme.dither * c * p * np.maximum(np.abs(R), 0.5) ** (p - 1)
    if not np.all(np.abs(pred - d.y) <= slack):
        return False
    for name, printed in d.num.items():
        sim_v = out.diagnostics.get(name)
        if sim_v is not None and sim_v.dtype != object:
            ok = np.isfinite(printed)
            tol = np.array([token_value(str(x))[1] if token_value(str(x)) else 0.0 for x in printed[ok]])  # type: ignore[index]
            if np.any(np.abs(sim_v.astype(float)[ok] - printed[ok]) > tol + 1e-6):
                return False
    for name, printed in d.cat.items():
        sim_c = out.diagnostics.get(name)
        if sim_c is not None and sim_c.dtype == object:
            ok = np.array([x is not None for x in printed])
            if np.any(sim_c[ok] != printed[ok]):
                return False
    return True


# -- the attacks --------------------------------------------------------------------------------------
_CACHE: dict[str, Fit | str] = {}  # fits by what they read (see _fingerprint): a transcript audited twice fits once
_CACHE_SIZE = 64


def _fingerprint(v: View, mode: str) -> str:
    """Everything a fit reads: the shown entries, the provider's answers, the first request (its
    wording and sampling seed), the task's env and declaration, the box and the limits."""
    task = v.task
    decl = json.dumps(task.spec.model_dump(mode="json"), sort_keys=True, default=str) if task is not None and task.spec is not None else ""
    parts = [mode, v.facts.task, decl, repr(v.box), repr(v.memo.get("sim_limits")),
             v.requests[0].text if v.requests else "", repr(v.requests[0].seed if v.requests else None)]
    parts += [repr((tuple(e.params), tuple(e.tols), e.ret, e.ret_tol, sorted(e.diagnostics.items()), e.first_call, e.components))
              for e in v.entries]
    parts += [repr((r.iteration, r.attempt, r.form, r.answer)) for r in v.requests]
    return hashlib.sha256("\x00".join(parts).encode()).hexdigest()


def fit_view(v: View, mode: str) -> Fit | str:
    """The fit of ``mode`` ("exact" or "marginal"), memoised in the view and, by what it reads, in
    this process; a string: why it did not run."""
    key = f"sim-{mode}"
    if key in v.memo:
        return v.memo[key]  # type: ignore[return-value]
    digest = _fingerprint(v, mode)
    result = _CACHE.get(digest)
    if result is None:
        result = _run_fit(v, mode)
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[digest] = result
    v.memo[key] = result
    return result


def _run_fit(v: View, mode: str) -> Fit | str:
    task = v.task
    if task is None:
        from ..errors import PPPropsError
        from ..tasks import get_task

        try:
            task = get_task(v.facts.task)
        except PPPropsError:
            return f"fact unknown: task {v.facts.task!r} is not known here, so its env cannot be built"
    schemes = schemes_of(v)
    if not schemes:
        return "the prompt shows raw values (nothing to fit)"
    if len(v.entries) < 3:
        return f"only {len(v.entries)} shown entries"
    limits: SimLimits = v.memo.get("sim_limits") or DEFAULT_LIMITS  # type: ignore[assignment]
    probe = Budget(1)
    sim, why = simulator_for(task, probe)
    if sim is None:
        return why
    sim.budget = limits.budget(sim.kind)
    prior = RewardPrior(S=_reward_scale(task))
    try:
        if mode == "exact":
            d, seeds, how = known_seeds(v, sim)
            if d is None or seeds is None:
                return how
            if len(schemes) > 1:  # the document form names no encoding: the warm-up that matched does
                encoded = np.isnan(d.raw).all()
                schemes = [x for x in schemes if (x.params == "scale") != encoded] or schemes
            fit = search(v, d, sim, seeds, 1, schemes, exact=True, prior=prior)
        else:
            d = observed(v)
            how = f"{MARGINAL_EPISODES} episodes per shown policy from the public initial-state distribution"
            draws = np.random.default_rng(MARGINAL_SEED).integers(0, 2**31, size=MARGINAL_EPISODES)
            seeds = np.tile(draws, len(d.y))
            fit = search(v, d, sim, seeds, MARGINAL_EPISODES, schemes, exact=False, prior=prior)
    except OverBudget as e:
        return f"over its budget before a first fit ({e.what})"
    finally:
        sim.close()
    fit.notes.append(how)
    return fit


def _reward_scale(task: Any) -> float:
    """The public bound S of the reward origins (``client.hardening.reward_scale``: |optimal return|,
    else a per-task constant; a task file may declare it as its ``reward_scale`` fact)."""
    from ..client.hardening import reward_scale

    return float(reward_scale(task))


def _detail(fit: Fit, mode: str) -> str:
    how = fit.notes[0] if fit.notes else ""
    verdict = ("reproduces every printed return within its precision" if fit.exact
               else f"best fit: RMS residual {fit.rms:.3g} printed units")
    stop = f"; stopped {fit.stopped}" if fit.stopped else ""
    return (f"{mode} simulator fit ({fit.scheme.params} parameters, {fit.scheme.rewards} rewards): {verdict}; {how}; "
            f"{fit.steps:.3g} simulated steps{stop}")


def _raw_guesses(v: View, fit: Fit) -> tuple[RawGuess, ...]:
    """The raw return and parameters the fit decodes for each shown entry it used."""
    out = []
    for k, pos in enumerate(fit.entries):
        e = v.entries[pos]
        out.append(RawGuess(tuple(float(x) for x in e.params), tuple(float(t) for t in e.tols), e.ret,
                            float(fit.raw_returns[k]), tuple(float(x) for x in fit.raw_params[k])))
    return tuple(out)


def sim_exact(v: View) -> Estimate:
    """c (with s, p, and raw values) by simulating the shown policies on their known initial states."""
    return _estimate(v, "exact", "c")


def sim_exact_a(v: View) -> Estimate:
    """a_j (with the offsets m) from the same fit as ``sim-exact``."""
    return _estimate(v, "exact", "a")


def sim_marginal(v: View) -> Estimate:
    """c (with s, p) by simulating the shown policies on public initial-state draws."""
    return _estimate(v, "marginal", "c")


def sim_marginal_lattice(v: View) -> Estimate:
    """c (with s, p) from the ``sim-marginal`` fit's hypothesis by the exact likelihood of returns
    on a lattice (``lattice_posterior``); not run when the printed returns are not such."""
    fit = fit_view(v, "marginal")
    name = "sim-marginal-lattice"
    if isinstance(fit, str):
        return Estimate(name, "c", None, fit, not_run=fit)
    if fit.lattice is None:
        why = "the printed returns are not on a lattice under a warped map (nothing for the exact likelihood to read)"
        return Estimate(name, "c", None, why, not_run=why)
    c, s, p = fit.lattice
    detail = (f"posterior median of the exact likelihood of the printed returns on {LATTICE_EPISODES} episodes of each policy "
              f"the marginal fit decodes ({_detail(fit, 'marginal')})")
    return Estimate(name, "c", c, detail, extras={"s": s, "p": p}, raw=_lattice_guesses(v, fit))


def _lattice_guesses(v: View, fit: Fit) -> tuple[RawGuess, ...]:
    """Each printed return the fit used, read back through the lattice reading's map: the raw
    return x = w_p^-1(y / c + w_p(s)) at the nearest lattice point (the dither's step), with the
    raw parameters the fit decodes. The map's secrets trade off against each other, so the
    returns can be read closer than c (docs/threat-model.md)."""
    assert fit.lattice is not None
    c, s, p = fit.lattice
    step = fit.scheme.dither
    out = []
    for k, pos in enumerate(fit.entries):
        e = v.entries[pos]
        x = float(_w(e.ret / c + _w(s, p), 1.0 / p))
        out.append(RawGuess(tuple(float(t) for t in e.params), tuple(float(t) for t in e.tols), e.ret,
                            round(x / step) * step if step > 0 else x, tuple(float(t) for t in fit.raw_params[k])))
    return tuple(out)


def sim_marginal_a(v: View) -> Estimate:
    """a_j from the same fit as ``sim-marginal``."""
    return _estimate(v, "marginal", "a")


def _estimate(v: View, mode: str, target: str) -> Estimate:
    name = f"sim-{mode}" + ("-a" if target == "a" else "")
    fit = fit_view(v, mode)
    if isinstance(fit, str):
        return Estimate(name, target, None, fit, not_run=fit)
    detail = _detail(fit, mode)
    guesses = _raw_guesses(v, fit)
    if target == "c":
        extras = {"s": fit.s, "p": fit.p} if fit.scheme.rewards != "scale" else {}
        extras["misfit"] = fit.misfit  # how well the fit explains the printed returns (exposure.raw_exposures reads it)
        return Estimate(name, "c", fit.c, detail, extras=extras, raw=guesses)
    a = fit.a.copy()
    return Estimate(name, "a", a, detail, raw=guesses,
                    extras={f"m{j}": float(x) for j, x in enumerate(fit.m)} if fit.m is not None else {})
