"""Which implemented attacks recover a hidden secret of a run within 1%: the audit fails on those.

The attacks read the transcript only (``privacy.attacks``); their estimates are scored here
against the run's true secrets: from the key file when it is in the run directory, otherwise, for
the paper's pure scales, from the store's raw and encoded values (c = r~ / r, a_j = theta~_j / theta_j).
Only secrets the preset hides are scored: c when rewards are scaled, a when parameters are encoded.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..client.secrets import Secrets
from ..methods import Mechanisms
from ..values import Candidate
from .attacks import TARGET, run_attacks
from .transcript import Request

EXPOSED_WITHIN = 0.01  # an attack that recovers a secret within 1% fails the audit

# Channels that PP-ProPS as the paper defines it keeps (unscaled diagnostics, integer returns and
# caps under a pure scale, the warm-up's uniform box, clipping to the box); the others come from how
# an implementation seeds its draws (this one fixed the request seed and the fallback noise).
PAPER_CHANNELS = frozenset({"diagnostic", "lattice", "warped-lattice", "known-cap", "additivity", "survive-length",
                            "saturated-ctrl", "warmup-range", "clip-edge"})


@dataclass(frozen=True)
class Exposure:
    """How much one attack recovered of a secret in one run: the median relative error, the
    coordinates estimated within 1%, and whether the paper's scheme itself keeps this channel.
    """

    attack: str
    target: str  # c or a
    error: float  # median relative error (a: over the coordinates it estimated)
    coords: int  # a: coordinates estimated within 1% (c: 1)
    detail: str
    paper: bool  # a channel the paper's scheme itself keeps


def true_secrets(mech: Mechanisms, cands: Sequence[Candidate], secrets: Secrets | None) -> tuple[float | None, np.ndarray | None]:
    """(c, a) to score against: the key file's, else the store's ratios when the maps are pure scales."""
    if secrets is not None:
        return float(secrets.c), np.asarray(secrets.a, dtype=np.float64)
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


def exposures(requests: Sequence[Request], task: str, box: tuple[float, float], mech: Mechanisms,
              cands: Sequence[Candidate], secrets: Secrets | None) -> tuple[list[Exposure], str]:
    """Attacks that recover a hidden secret within 1%, and a note when scoring was not possible."""
    true_c, true_a = true_secrets(mech, cands, secrets)
    if true_c is None and true_a is None:
        return [], "attacks not scored: no key file and the maps are not pure scales"
    out = []
    for est in run_attacks(requests, task, box):
        if not est.applicable or est.value is None:
            continue
        if TARGET[est.attack] == "c":
            if not mech.scale_rewards or true_c is None:
                continue
            err = abs(float(est.value) / true_c - 1)
            if err <= EXPOSED_WITHIN:
                out.append(Exposure(est.attack, "c", err, 1, est.detail, est.attack in PAPER_CHANNELS))
        else:
            if not mech.encode_params or true_a is None:
                continue
            v = np.asarray(est.value, dtype=np.float64)
            known = np.isfinite(v) & (v > 0) & np.isfinite(true_a)
            if not known.any():
                continue
            errs = np.abs(v[known] / true_a[known] - 1)
            err = float(np.median(errs))
            if err <= EXPOSED_WITHIN:
                out.append(Exposure(est.attack, "a", err, int(np.sum(errs <= EXPOSED_WITHIN)), est.detail,
                                    est.attack in PAPER_CHANNELS))
    return out, ""
