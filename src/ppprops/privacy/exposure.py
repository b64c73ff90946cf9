"""Which implemented attacks recover a hidden secret or a raw value of a run within 1%: the audit fails on those.

The attacks read the transcript only (``privacy.attacks``; the simulator attacks also build the
task's env when it is public); their estimates are scored here against the run's true values:
the secrets from the key file when it is in the run directory, otherwise, for the paper's pure
scales, from the store's raw and encoded values (c = r~ / r, a_j = theta~_j / theta_j); raw
returns and parameters from the store. Only secrets the preset hides are scored: c when rewards
are scaled, a when parameters are encoded; raw values when the preset encodes them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..client.secrets import Secrets
from ..methods import Mechanisms
from ..values import Candidate
from .attacks import SIMULATOR_ATTACKS, TARGET, run_attacks
from .requests import Request
from .simfit import SimLimits
from .tokens import renders
from .view import Estimate, RawGuess

if TYPE_CHECKING:
    from ..tasks.base import Task

EXPOSED_WITHIN = 0.01  # an attack that recovers a secret (or a raw value) within 1% fails the audit
NEAR_MISS = 0.02  # within 2% (and not 1%): named in the verdict's line, the run still CLEAN
PRIOR = 1.0  # the prior guess of c and a_j (the geometric mean of both schemes' distributions)
# Attacks whose raw reading of the best shown entry is scored against the store (``raw_exposures``):
# the exact fit reproduces each episode, the lattice reading names each printed return's raw value.
RAW_READERS = frozenset({"sim-exact", "sim-marginal-lattice"})

# Channels that PP-ProPS as the paper defines it keeps (unscaled diagnostics, integer returns and
# caps under a pure scale, the warm-up's uniform box, clipping to the box); the others come from how
# an implementation seeds its draws (this one fixed the request seed and the fallback noise), or, for
# the simulator attacks, from a public env, which no encoding of the paper's or pp-hardened's closes.
PAPER_CHANNELS = frozenset({"diagnostic", "lattice", "warped-lattice", "known-cap", "additivity", "survive-length",
                            "saturated-ctrl", "warmup-range", "clip-edge"})


@dataclass(frozen=True)
class Exposure:
    """How much one attack recovered in one run: ``target`` "c", "a", "raw return" (the best shown
    policy's raw return) or "raw params" (its raw parameters); ``error`` the relative error (a: the
    median over the coordinates it estimated; raw params: the largest error as a share of the box
    width); ``coords`` the coordinates within 1% (c and raw values: 1); whether the paper's scheme
    itself keeps this channel."""

    attack: str
    target: str
    error: float
    coords: int
    detail: str
    paper: bool


@dataclass(frozen=True)
class SimOutcome:
    """What one simulator attack recovered on a run, exposing or not: errors of c and a (error
    factor - 1, as ``privacy.matrix``), the prior guess's errors, and the raw return's."""

    attack: str
    target: str
    error: float | None  # None: not scored (no key file for a warped run)
    prior_error: float | None
    raw_return_error: float | None = None


@dataclass
class Assessment:
    """Every attack's outcome on one run: the exposures (within 1%), the attacks that could not
    run and why, what the simulator attacks recovered, and a note when scoring was not possible."""

    exposures: list[Exposure] = field(default_factory=list)
    not_run: list[tuple[str, str]] = field(default_factory=list)
    simulated: list[SimOutcome] = field(default_factory=list)
    estimates: list[Estimate] = field(default_factory=list)
    note: str = ""
    near_misses: list[str] = field(default_factory=list)  # "attack: what within x%", for errors in (1%, 2%]


def true_secrets(mech: Mechanisms, cands: Sequence[Candidate], secrets: Secrets | None,
                 grid: float = 1.0) -> tuple[float | None, np.ndarray | None]:
    """(c, a) to score against: the key file's, else the store's ratios when the maps are pure scales.
    ``grid``: the run's secret grid factor g (1 off the grid); a is then the effective scale g a_j,
    what decoding a shown value needs (``client.codec.grid_factor``)."""
    if secrets is not None:
        return float(secrets.c), grid * np.asarray(secrets.a, dtype=np.float64)
    pure = not (mech.secret_offsets or mech.warp_params or mech.warp_rewards)
    if not pure or not cands:
        return None, None
    rets = [(c.feedback_enc.ret, c.ret) for c in cands if c.ret != 0 and np.isfinite(c.ret)]
    c = float(np.median([e / r for e, r in rets])) if rets else None
    P = np.array([c.params for c in cands])
    E = np.array([c.params_enc for c in cands])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.where(np.abs(P) > 1e-9, E / P, np.nan)
    a = np.nanmedian(ratios, axis=0)
    return c, a


def error_factor(est: float | np.ndarray, true: float | np.ndarray) -> np.ndarray:
    """Symmetric error factor minus one: exp(|ln(est/true)|) - 1 (0.01 = within 1%, 1.0 = off by 2x either way)."""
    return np.expm1(np.abs(np.log(np.asarray(est, dtype=np.float64) / true)))


def shown_candidate(g: RawGuess, cands: Sequence[Candidate]) -> Candidate | None:
    """The candidate a shown entry stands for: its printed encoded parameters render that
    candidate's; among several (a policy evaluated twice), the one whose encoded return is nearest
    the printed one."""
    hits = []
    for c in cands:
        enc = np.asarray(c.params_enc, dtype=np.float64)
        if len(enc) == len(g.params) and all(renders(float(x), p, t) for x, p, t in zip(enc, g.params, g.tols, strict=True)):
            hits.append(c)
    if not hits:
        return None
    return min(hits, key=lambda c: abs(c.feedback_enc.ret - g.ret) if math.isfinite(c.feedback_enc.ret) else math.inf)


def raw_exposures(est: Estimate, cands: Sequence[Candidate], box: tuple[float, float]) -> list[Exposure]:
    """The raw values an attack decodes for the best shown policy (highest printed return), scored
    against the store: its raw return within 1%, its raw parameters within 1% of the box width."""
    if not est.raw:
        return []
    best = max(est.raw, key=lambda g: g.ret)
    c = shown_candidate(best, cands)
    if c is None or not math.isfinite(c.ret):
        return []
    out = []
    if c.ret != 0 and math.isfinite(best.raw_ret):
        err = abs(best.raw_ret - c.ret) / abs(c.ret)
        if err <= EXPOSED_WITHIN:
            out.append(Exposure(est.attack, "raw return", err, 1, est.detail, False))
    P = np.asarray(best.raw_params, dtype=np.float64)
    if len(P) == len(c.params) and np.all(np.isfinite(P)):
        err = float(np.max(np.abs(P - np.asarray(c.params)))) / (box[1] - box[0])
        if err <= EXPOSED_WITHIN:
            out.append(Exposure(est.attack, "raw params", err, len(P), est.detail,
                                False))
    return out


def assess(requests: Sequence[Request], task: str | Task, box: tuple[float, float], mech: Mechanisms,
           cands: Sequence[Candidate], secrets: Secrets | None, *, limits: SimLimits | None = None,
           simulate: bool = True, grid: float = 1.0) -> Assessment:
    """Run every attack on the transcript (``attacks.run_attacks``, simulator attacks bounded by
    ``limits``) and score it: see ``Assessment``. ``grid``: the run's grid factor g (1 off the
    grid): estimates of a are scored against g a_j."""
    out = Assessment()
    true_c, true_a = true_secrets(mech, cands, secrets, grid)
    if true_c is None and true_a is None:
        out.note = "secrets not scored: no key file and the maps are not pure scales (raw values are still scored)"
    out.estimates = run_attacks(requests, task, box, limits=limits, simulate=simulate)
    for est in out.estimates:
        if est.not_run:
            out.not_run.append((est.attack, est.not_run))
            continue
        if mech.encode_params and est.attack in RAW_READERS:
            out.exposures += raw_exposures(est, cands, box)
        if not est.applicable or est.value is None:
            continue
        if TARGET[est.attack] == "c":
            if not mech.scale_rewards or true_c is None:
                continue
            err = float(error_factor(float(est.value), true_c))
            if EXPOSED_WITHIN < err <= NEAR_MISS:
                out.near_misses.append(f"{est.attack}: c within {100 * err:.3g}%")
            if est.attack in SIMULATOR_ATTACKS:
                out.simulated.append(SimOutcome(est.attack, "c", err, float(error_factor(PRIOR, true_c))))
            if err <= EXPOSED_WITHIN:
                out.exposures.append(Exposure(est.attack, "c", err, 1, est.detail, est.attack in PAPER_CHANNELS))
        else:
            if not mech.encode_params or true_a is None:
                continue
            v = np.asarray(est.value, dtype=np.float64)
            known = np.isfinite(v) & (v > 0) & np.isfinite(true_a)
            if not known.any():
                continue
            errs = error_factor(v[known], true_a[known])
            err = float(np.median(errs))
            if EXPOSED_WITHIN < err <= NEAR_MISS:
                out.near_misses.append(f"{est.attack}: a within {100 * err:.3g}%")
            if est.attack in SIMULATOR_ATTACKS:
                out.simulated.append(SimOutcome(est.attack, "a", err, float(np.median(error_factor(PRIOR, true_a[known])))))
            if err <= EXPOSED_WITHIN:
                out.exposures.append(Exposure(est.attack, "a", err, int(np.sum(errs <= EXPOSED_WITHIN)), est.detail,
                                              est.attack in PAPER_CHANNELS))
    return out


def exposures(requests: Sequence[Request], task: str | Task, box: tuple[float, float], mech: Mechanisms,
              cands: Sequence[Candidate], secrets: Secrets | None, *, limits: SimLimits | None = None) -> tuple[list[Exposure], str]:
    """Attacks that recover a hidden secret or a raw value within 1%, and a note when scoring was not possible."""
    a = assess(requests, task, box, mech, cands, secrets, limits=limits)
    return a.exposures, a.note
