"""The run seed, when a transcript gives it away, and the warm-up replayed from it.

The paper's warm-up (and the hardened encoded one) is drawn from ``seeding.rng(seed, WARMUP, m)``,
and each candidate's episodes from ``seeding.episode_seeds(seed, index, episodes)``: whoever knows
the run seed replays both. A provider finds a small run seed from what the first prompt shows:
an encoded warm-up prints the draws themselves (a table lookup), the paper's raw warm-up prints
a_j times them (the signs, then one consistent scale per coordinate); transcripts of older runs
also carried a sampling seed derived from the run seed.
"""

from __future__ import annotations

import functools
import re
from typing import Any

import numpy as np

from .. import seeding
from .tokens import token_value
from .view import View

SEED_SEARCH = 1 << 16  # run seeds tried against the request's sampling seed
SEED_SEARCH_BLIND = 2048  # run seeds tried against the warm-up when no sampling seed was sent
WARMUP_REPLAY = 32  # warm-up samples replayed per seed
BLIND_SAMPLES = 12  # warm-up samples per seed compared when searching blind (warm-ups are rarely longer)
ASSIGN_NODES = 20_000  # steps of the search that matches warm-up entries to draws under one scale
RANGE_STATED = re.compile(r"(?:must lie in|drawn uniformly from) \[([^\],]+), ([^\]]+)\]")


def find_run_seed(v: View) -> tuple[int | None, str]:
    """The run seed, if the transcript gives it away: from the request's sampling seed when that was
    derived from the run seed (``seeding.llm_seed``, in older runs), else by trying small seeds
    against the sign pattern of the warm-up (drawn from the run seed under the paper's warm-up)."""
    if "run_seed" not in v.memo:
        v.memo["run_seed"] = _find_run_seed(v)
    return v.memo["run_seed"]  # type: ignore[return-value]


@functools.cache
def _seed_field_table() -> dict[int, int]:
    """``llm_seed(s, 0, 0) -> s`` for every run seed searched (built once per process)."""
    return {seeding.llm_seed(s, 0, 0): s for s in range(SEED_SEARCH)}


@functools.cache
def _warmup_draws(D: int, lo: Any, hi: Any) -> np.ndarray:
    """The first BLIND_SAMPLES warm-up draws of every run seed searched blind, shape (seeds, samples, D)."""
    lo, hi = (np.asarray(b, dtype=np.float64) if isinstance(b, tuple) else b for b in (lo, hi))  # an MLP's per-coordinate bounds
    return np.array([[seeding.rng(s, seeding.WARMUP, m).uniform(lo, hi, size=D) for m in range(BLIND_SAMPLES)]
                     for s in range(SEED_SEARCH_BLIND)])


def _find_run_seed(v: View) -> tuple[int | None, str]:
    first = v.requests[0] if v.requests else None
    if first is not None and first.seed is not None:
        if (first.iteration, first.attempt) == (0, 0):
            found = _seed_field_table().get(first.seed)
        else:
            found = next((s for s in range(SEED_SEARCH) if seeding.llm_seed(s, first.iteration, first.attempt) == first.seed), None)
        if found is not None:
            return found, f"run seed {found} recovered from the request's sampling seed"
    if not v.warmup:
        return None, "no warm-up entries"
    W = np.array([e.params for e in v.warmup])
    tol = np.array([e.tols for e in v.warmup])
    need = min(3, len(W))
    # an encoded warm-up (pp-hardened) prints the draws themselves: look them up exactly
    lo_w, hi_w = warmup_box(v)
    draws = _warmup_draws(v.D, lo_w, hi_w)  # (seeds, samples, D)
    hits = np.zeros(SEED_SEARCH_BLIND, dtype=int)
    for i, w in enumerate(W):
        hits += np.any(np.all(np.abs(draws - w) <= tol[i] * (1 + 1e-9) + 1e-12, axis=2), axis=1)
    exact = np.flatnonzero(hits >= need)
    if len(exact):
        s = int(exact[0])
        return s, (f"run seed {s} found by looking up the encoded warm-up among the draws of run seeds "
                   f"0..{SEED_SEARCH_BLIND - 1}")
    # the paper's raw warm-up prints a_j times the draws: signs first, then one scale per coordinate
    lo, hi = (tuple(b.tolist()) if isinstance(b, np.ndarray) else b for b in v.init_box)  # an MLP's: per layer (cached: hashable)
    raw = _warmup_draws(v.D, lo, hi)
    signs = np.sign(raw)
    ok = np.ones(SEED_SEARCH_BLIND, dtype=bool)
    for i, w in enumerate(W[:3]):
        live = np.abs(w) > tol[i]
        ok &= np.any(np.all(signs[:, :, live] == np.sign(w[live]), axis=2), axis=1)
    for hit in np.flatnonzero(ok):
        if _scales_consistently(W, tol, raw[hit], need):
            return int(hit), (f"run seed {int(hit)} found by trying seeds 0..{SEED_SEARCH_BLIND - 1} on the warm-up "
                            "(signs, and one scale per coordinate)")
    return None, f"tried run seeds 0..{SEED_SEARCH_BLIND - 1} on the warm-up: none matches"


def warmup_box(v: View) -> tuple[float, float]:
    """The box the warm-up was drawn from as the prompt states it (an encoded warm-up), else the public box."""
    for r in v.requests[:1]:
        m = RANGE_STATED.search(r.text)
        if m:
            lo, hi = token_value(m.group(1)), token_value(m.group(2))
            if lo and hi and hi[0] > lo[0]:
                return lo[0], hi[0]
    lo_b, hi_b = v.box
    half = (hi_b - lo_b) / 2
    return -half, half


def _scales_consistently(W: np.ndarray, tol: np.ndarray, draws: np.ndarray, need: int) -> bool:
    """Whether ``need`` shown warm-up entries are draws times one positive scale per coordinate."""
    return len(_assign(W, tol, draws)[0]) >= need


def _assign(W: np.ndarray, tol: np.ndarray, draws: np.ndarray) -> tuple[dict[int, int], tuple[np.ndarray, np.ndarray]]:
    """Shown warm-up entry -> the draw it is, under one positive scale per coordinate (interval
    arithmetic on the printed precision: each entry matched to a draw narrows every scale's
    interval). A depth-first search over the draws each entry could be (fewest first, each draw
    used once, at most ``ASSIGN_NODES`` steps); an entry that fits no draw is left out. Returns the
    largest consistent assignment and the scale intervals (low, high), each shape (D,)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        A = np.where(np.abs(draws)[None] > 0, (W - tol)[:, None, :] / draws[None], -np.inf)  # (entries, draws, D)
        B = np.where(np.abs(draws)[None] > 0, (W + tol)[:, None, :] / draws[None], np.inf)
    low_all, high_all = np.minimum(A, B), np.maximum(A, B)
    start = (np.zeros(W.shape[1]), np.full(W.shape[1], np.inf))

    def fits(i: int, lo_q: np.ndarray, hi_q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo_i, hi_i = np.maximum(low_all[i], lo_q), np.minimum(high_all[i], hi_q)
        ok = np.all(lo_i <= hi_i, axis=1) & np.all(hi_i > 0, axis=1)
        return np.flatnonzero(ok), lo_i, hi_i

    order = sorted(range(len(W)), key=lambda i: len(fits(i, *start)[0]))
    best: tuple[dict[int, int], tuple[np.ndarray, np.ndarray]] = ({}, start)
    nodes = 0

    def dfs(pos: int, lo_q: np.ndarray, hi_q: np.ndarray, current: dict[int, int]) -> bool:
        nonlocal best, nodes
        nodes += 1
        if len(current) > len(best[0]):
            best = (dict(current), (lo_q, hi_q))
        if pos == len(order):
            return True
        if nodes > ASSIGN_NODES:
            return False
        i = order[pos]
        found, lo_i, hi_i = fits(i, lo_q, hi_q)
        cand = [int(m) for m in found if m not in current.values()]
        if not cand:
            return dfs(pos + 1, lo_q, hi_q, current)
        for m in cand:
            current[i] = m
            if dfs(pos + 1, lo_i[m], hi_i[m], current):
                return True
            del current[i]
        return False

    dfs(0, *start, {})
    return best


def replay_warmup(v: View, seed: int) -> tuple[dict[int, int], np.ndarray | None, np.ndarray | None]:
    """For run seed ``seed``: (position in ``View.entries`` -> warm-up draw index, raw draws, encoded
    draws). An encoded warm-up (its entries are the draws of the stated encoded box) gives the
    encoded draws and no raw ones; the paper's warm-up gives the raw draws of the public box
    (matched on signs and a consistent scale)."""
    lo_w, hi_w = warmup_box(v)
    enc = np.array([seeding.rng(seed, seeding.WARMUP, m).uniform(lo_w, hi_w, size=v.D) for m in range(WARMUP_REPLAY)])
    pos = {id(e): k for k, e in enumerate(v.entries)}
    out: dict[int, int] = {}
    for e in v.warmup:
        hit = np.flatnonzero(np.all(np.abs(enc - e.params) <= np.asarray(e.tols) * (1 + 1e-9) + 1e-12, axis=1))
        if len(hit) == 1 and id(e) in pos:
            out[pos[id(e)]] = int(hit[0])
    if len(out) >= min(3, len(v.warmup)):
        return out, None, enc
    lo, hi = v.box
    raw = np.array([seeding.rng(seed, seeding.WARMUP, m).uniform(lo, hi, size=v.D) for m in range(WARMUP_REPLAY)])
    a, _ = replay_scale(v, seed)
    if a is None:
        return {}, None, None
    for e in v.warmup:
        hit = np.flatnonzero(np.all(np.abs(a * raw - e.params) <= 2 * np.asarray(e.tols) + 0.02 * np.abs(e.params), axis=1))
        if len(hit) == 1 and id(e) in pos:
            out[pos[id(e)]] = int(hit[0])
    return out, raw, None


def replay_scale(v: View, seed: int) -> tuple[np.ndarray | None, str]:
    """a_j of the paper's warm-up replayed from run seed ``seed``: shape (D,), or None with why.

    Each shown warm-up entry is matched to the one raw draw it is under one positive scale per
    coordinate (``_assign``); a_j = the middle of the interval of scales every match allows at the
    printed precision (least squares of shown over raw where that interval is open), accepted when
    it rescales every matched draw onto its entry within the printed precision (2% slack). An encoded warm-up gives
    a = 1: its draws are what is shown.
    """
    lo, hi = v.init_box
    W = np.array([e.params for e in v.warmup])
    tol = np.array([e.tols for e in v.warmup])
    raw = np.array([seeding.rng(seed, seeding.WARMUP, m).uniform(lo, hi, size=v.D) for m in range(WARMUP_REPLAY)])
    found, (lo_q, hi_q) = _assign(W, tol, raw)
    pairs = sorted(found.items())
    if len(pairs) < min(3, len(W)):
        return None, "the replay does not match the warm-up"
    num = sum(W[i] * raw[m] for i, m in pairs)
    den = sum(raw[m] ** 2 for _, m in pairs)
    # the middle of the scales every matched entry allows (at the printed precision), else least squares
    a = np.where(np.isfinite(hi_q) & (lo_q > 0), (lo_q + hi_q) / 2, num / den)
    resid = max(float(np.max(np.abs(W[i] - a * raw[m]) - 2 * tol[i] - 0.02 * np.abs(W[i]))) for i, m in pairs)
    if resid <= 0 and np.all(a > 0):
        return a, f"{len(pairs)} warm-up entries replayed"
    return None, "the replay does not scale onto the warm-up"
