"""The only producer of wire values: encodes raw candidates into what the LLM may see, decodes answers.

The paper's maps (Sec. II-B, II-C) are theta~ = A theta and r~ = c r. The hardening switches of
``ppprops.methods`` extend them (docs/threat-model.md):

- secret offsets: theta~ = A (theta - m), r~ = c (r - s);
- warped parameters: theta~ = A (T(theta) - T(m)), where T maps the open public box onto the
  whole real line (T(u) = W/pi tan(pi (u - lo)/W - pi/2), slope 1 at the centre). Every encoded
  value decodes strictly inside the box, so no answer is ever clipped, and encoded values are
  clamped to +-ENCODED_LIMIT, a public bound, so an extreme answer never echoes back a secret;
- warped rewards: r~ = c (w_p(r + d(r)) - w_p(s)), w_p(x) = sign(x) |x|^p, an increasing map
  (ranking kept). d(r) is a secret dither, a keyed pseudo-random function of the value in
  (-h/2, h/2) for a quantity whose public resolution is h (integer returns: h = 1 per episode), so
  no integer structure survives the warp (the warped-lattice attack) while distinct values keep
  their order and equal values stay equal. Each reward component gets a map of its own
  (c_k, s_k, p_k, derived from the key), so anchors and relations of different components never
  add up to one map (the additivity attack);
- hidden components: one reward component (the task's residual) is never shown, so the return is
  not the sum of what is shown.
- the grid (the ``grid`` number format, ``wire.numbers``): every encoded parameter is also
  multiplied by one secret global factor g = G u, so the prompt writes it as an integer. G (public,
  ``public_scale``) maps the largest encoded value the box allows under the secrets' prior
  (a_j <= 10, or 3 when warped) to GRID_SPAN = 999; u is keyed by the secrets, log-uniform on
  [1/2, 1], so no value leaves [-999, 999] under ``pp`` and g is not a function of anything public.
  The factor is global, not one per coordinate: a grid per coordinate would make each step a_j's;
  a global one only rescales A (theta~ = g A theta), and g is no more recoverable than A's overall
  scale. Public widths in the encoded space (the encoded warm-up box, the fallback noise) are
  multiplied by G, never by g;
Every map is increasing in each coordinate, so larger encoded values still mean larger raw ones.
The request's sampling seed is derived from the key as well, never from the run seed alone.
"""

from __future__ import annotations

import hashlib
import hmac
import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from ..values import Feedback
from ..wire.encoded import EncodedEntry
from ..wire.numbers import GRID_SPAN
from .secrets import HARDENED_A_LOG, HARDENED_P_LOG, LOG_HIGH, LOG_LOW, Secrets

ENCODED_LIMIT = 1.0e6  # public clamp of warped encoded parameters (answers beyond it decode as if at it)
# The encoded warm-up box of warped parameters is the raw box's width times the hardened prior's
# largest a_j (3): decoded through the warp, its draws then reach within about 0.8 of the box's
# edges at a_j = 1 (a box of 1x never went past 3.8 from the origin there), so the search can start
# from strong gains as the paper's raw uniform warm-up does (benchmark 16, Pendulum-v1, 10 seeds:
# final -1252.0 against -1321.1 with the 1x box and -1144.2 for pp). On the grid it spans exactly
# +-GRID_SPAN.
WARMUP_SPAN = round(math.exp(HARDENED_A_LOG[1]), 9)
GRID_U_LOG = (math.log(0.5), 0.0)  # ln u of the grid factor g = G u: log-uniform, keyed by the secrets


def grid_scale(box: tuple[float, float] | None, warp_params: bool) -> float:
    """G, the public nominal grid factor: GRID_SPAN over the largest encoded magnitude the public box
    allows under the secrets' prior (half the box width times the largest a_j, 10, or 3 when the
    parameters are warped). Public: a function of the box and the preset only."""
    half = (box[1] - box[0]) / 2.0 if box is not None else 6.0
    a_hi = round(math.exp(HARDENED_A_LOG[1] if warp_params else LOG_HIGH), 9)  # 3 or 10, exactly
    return GRID_SPAN / (half * a_hi)


def grid_factor(secrets: Secrets, box: tuple[float, float] | None, warp_params: bool) -> float:
    """g = G u, the secret global grid factor of a run on the grid: G = ``grid_scale(box, warp_params)``
    (public), u log-uniform on [1/2, 1] from an HMAC of every secret (``secrets.subkey("grid")``), so
    ``resume`` derives the same g and no public value (run seed, D, box) gives it. The effective
    scale of coordinate j, what decoding needs, is g a_j (the audit scores attacks against it)."""
    digest = hmac.new(secrets.subkey("grid"), b"u", hashlib.sha256).digest()
    lo, hi = GRID_U_LOG
    return grid_scale(box, warp_params) * math.exp(lo + (hi - lo) * int.from_bytes(digest[:8], "big") / 2.0**64)


class Codec:
    """theta~ = A theta and r~ = c r, each switched on by its own setting (identity when off)."""

    def __init__(
        self,
        secrets: Secrets,
        *,
        encode_params: bool,
        scale_rewards: bool,
        offsets: bool = False,
        warp_params: bool = False,
        warp_rewards: bool = False,
        box: tuple[float, float] | None = None,
        hidden_diagnostics: frozenset[str] = frozenset(),
        hidden_components: frozenset[str] = frozenset(),
        resolution: Mapping[str, float] | None = None,
        episodes: int = 1,
        reward_scale: float = 1000.0,
        grid: bool = False,
    ) -> None:
        """``secrets``: the run's key (``a`` of shape (D,) sets D). ``box``: the public (low, high) of
        every raw parameter, needed by ``warp_params``. ``resolution``: public step of each reward
        quantity per episode ("return" or a component name; integer returns: 1), dithered under
        ``warp_rewards``; a mean over ``episodes`` episodes has step 1/episodes of it.
        ``reward_scale``: bound of the component offsets s_k. ``grid`` (with ``encode_params``): the
        secret global grid factor g of the module docstring multiplies every encoded parameter.
        Raises ValueError when ``warp_params`` (with ``encode_params``) is on and ``box`` is None."""
        D = len(secrets.a)
        self._a = np.asarray(secrets.a, dtype=np.float64) if encode_params else np.ones(D)
        self._c = float(secrets.c) if scale_rewards else 1.0
        self._m = secrets.origin if (offsets and encode_params) else np.zeros(D)
        self._s = secrets.reward_origin if (offsets and scale_rewards) else 0.0
        self._p = secrets.exponent if (warp_rewards and scale_rewards) else 1.0
        self.encode_params = encode_params
        self.scale_rewards = scale_rewards
        self.offsets = offsets
        self.warp_params = warp_params and encode_params
        self.warp_rewards = warp_rewards and scale_rewards
        self.hidden_diagnostics = frozenset(hidden_diagnostics)
        self.hidden_components = frozenset(hidden_components)
        self._resolution = {k: float(v) for k, v in (resolution or {}).items()} if self.warp_rewards else {}
        self._episodes = max(1, int(episodes))
        self._reward_scale = abs(float(reward_scale))
        self._seed_key = secrets.subkey("sampling-seed")
        self._reward_key = secrets.subkey("rewards")
        self._maps: dict[str, tuple[float, float, float]] = {}
        self.grid = grid and encode_params
        self.public_scale = grid_scale(box, self.warp_params) if self.grid else 1.0  # G (public)
        # the public encoded warm-up box's scale over the raw box (context.warmup_box): G, times the
        # prior's largest a_j when the parameters are warped (WARMUP_SPAN)
        self.warmup_scale = self.public_scale * (WARMUP_SPAN if self.warp_params else 1.0)
        self._g = grid_factor(secrets, box, self.warp_params) if self.grid else 1.0  # g = G u (secret)
        if self.warp_params:
            if box is None:
                raise ValueError("warped parameters need the public box")
            self._lo, self._hi = float(box[0]), float(box[1])
            self._m_t = self._t(self._m)

    def __repr__(self) -> str:
        return (f"Codec(encode_params={self.encode_params}, scale_rewards={self.scale_rewards}, offsets={self.offsets}, "
                f"warp_params={self.warp_params}, warp_rewards={self.warp_rewards}, grid={self.grid})")

    # -- the box-to-line map T and its inverse (warped parameters) ---------------------------
    def _t(self, theta: NDArray[np.float64]) -> NDArray[np.float64]:
        w = self._hi - self._lo
        u = (np.clip(theta, self._lo, self._hi) - self._lo) / w
        with np.errstate(over="ignore", invalid="ignore"):
            return (w / math.pi) * np.tan(math.pi * (u - 0.5))

    def _t_inv(self, z: NDArray[np.float64]) -> NDArray[np.float64]:
        w = self._hi - self._lo
        return self._lo + w * (0.5 + np.arctan(math.pi * z / w) / math.pi)

    # -- parameters -----------------------------------------------------------------------
    def encode(self, theta: NDArray[np.floating]) -> NDArray[np.float64]:
        """theta~ = A theta (paper Eq. 5, Sec. II-B), clipped to +-ENCODED_LIMIT when warped, times
        the grid factor g on the grid.

        With secret offsets m (``pp-hardened``) it is A (theta - m), and with the parameter warp T
        as well A (T(theta) - T(m)) (docs/threat-model.md). ``theta``: raw parameters, shape (D,).
        Returns the encoded vector, shape (D,), float64. The identity when ``encode_params`` is off.

        Raises:
            ValueError: ``theta`` is not of shape (D,).
        """
        x = np.asarray(theta, dtype=np.float64)
        if x.shape != self._a.shape:
            raise ValueError(f"theta has shape {x.shape}; the codec encodes vectors of shape {self._a.shape}")
        if self.warp_params:
            return self._g * np.clip(self._a * (self._t(x) - self._m_t), -ENCODED_LIMIT, ENCODED_LIMIT)
        return self._g * (self._a * (x - self._m))

    def decode(self, theta_enc: NDArray[np.floating]) -> NDArray[np.float64]:
        """theta = A^-1 theta~ (paper Eq. 6), the inverse of ``encode``: shape (D,) in, shape (D,) float64 out.

        Under ``warp_params`` every real vector decodes into the open box (the LLM's answer cannot
        leave it); otherwise the caller clips the result into the box.
        """
        x = np.asarray(theta_enc, dtype=np.float64) / self._g
        if self.warp_params:
            return self._t_inv(np.clip(x, -ENCODED_LIMIT, ENCODED_LIMIT) / self._a + self._m_t)
        return x / self._a + self._m

    # -- rewards --------------------------------------------------------------------------
    def _prf(self, *parts: str) -> float:
        """A keyed pseudo-random number in [0, 1), fixed by ``parts`` (HMAC-SHA256 of the reward key)."""
        digest = hmac.new(self._reward_key, "\x00".join(parts).encode(), hashlib.sha256).digest()
        return int.from_bytes(digest[:8], "big") / 2.0**64

    def _map(self, quantity: str) -> tuple[float, float, float]:
        """(c, s, p) of one reward quantity: the key's own for the return, one of its own per component
        when rewards are warped (drawn like c, s and p from the key), else the return's."""
        if quantity == "return" or not self.warp_rewards:
            return self._c, self._s, self._p
        if quantity not in self._maps:
            u = [self._prf("component", quantity, k) for k in ("c", "s", "p-sign", "p")]
            c = math.exp(LOG_LOW + (LOG_HIGH - LOG_LOW) * u[0])
            s = (2.0 * u[1] - 1.0) * self._reward_scale if self.offsets else 0.0
            lo, hi = HARDENED_P_LOG
            p = math.exp((1.0 if u[2] < 0.5 else -1.0) * (lo + (hi - lo) * u[3]))
            self._maps[quantity] = (c, s, p)
        return self._maps[quantity]

    def _dither(self, r: float, quantity: str, step: float) -> float:
        """r + d, d in (-step/2, step/2): a keyed function of the exact value (ties stay ties)."""
        if step <= 0 or not math.isfinite(r):
            return r
        return r + (self._prf("dither", quantity, repr(r)) - 0.5) * step

    def scale(self, r: float, quantity: str = "return", *, per_episode: bool = False) -> float:
        """Encode one reward-valued number: a return (mean over the episodes, or one episode's with
        ``per_episode``), a component (``quantity`` = its name), the optimum when disclosed.

        r~ = c r for the return (paper Eq. 7) and each component (Eq. 8); with ``offsets``
        c (r - s), with ``warp_rewards`` the warped map of the module docstring. The identity
        when ``scale_rewards`` is off. Raw reward units in, encoded units out."""
        r = float(r)
        c, s, p = self._map(quantity)
        step = self._resolution.get(quantity, 0.0) / (1 if per_episode else self._episodes)
        if p == 1.0 and step == 0.0:
            return c * (r - s)
        return c * (_w(self._dither(r, quantity, step), p) - _w(s, p))

    def scale_components(self, components: Mapping[str, float]) -> dict[str, float]:
        """Every shown component through its map; hidden components are left out."""
        return {k: self.scale(v, k) for k, v in components.items() if k not in self.hidden_components}

    def sampling_seed(self, run_seed: int, iteration: int, attempt: int) -> int:
        """The request's sampling seed: keyed by the secrets, so it repeats on resume (and for the
        same key and run seed) but cannot be traced back to the run seed (docs/threat-model.md)."""
        msg = f"{int(run_seed)}/{int(iteration)}/{int(attempt)}".encode()
        return int.from_bytes(hmac.new(self._seed_key, msg, hashlib.sha256).digest()[:4], "big") >> 1

    def visible_diagnostics(self, diagnostics: Mapping[str, float | str]) -> dict[str, float | str]:
        """Diagnostics minus those that would pin the return or a reward component (hardened only)."""
        return {k: v for k, v in diagnostics.items() if k not in self.hidden_diagnostics}

    def entry(
        self,
        index: int,
        theta_enc: NDArray[np.floating],
        ret_enc: float,
        components_enc: Mapping[str, float],
        diagnostics: Mapping[str, float | str],
    ) -> EncodedEntry:
        """Wrap already-encoded values (as stored) into a wire entry."""
        return EncodedEntry(
            index=index,
            params=tuple(float(v) for v in theta_enc),
            ret=float(ret_enc),
            components=tuple((k, float(v)) for k, v in components_enc.items()),
            diagnostics=tuple((k, v) for k, v in self.visible_diagnostics(diagnostics).items()),
        )


def encode_feedback(codec: Codec, fb: Feedback) -> Feedback:
    """Encode every reward-valued field; diagnostics are not rewards and stay as they are (minus hidden ones)."""
    return Feedback(
        ret=codec.scale(fb.ret),
        components=codec.scale_components(fb.components),
        diagnostics=codec.visible_diagnostics(fb.diagnostics),
        episode_returns=tuple(codec.scale(r, per_episode=True) for r in fb.episode_returns),
    )


def _w(x: float, p: float) -> float:
    """The power warp sign(x) |x|^p (the identity for p = 1)."""
    return x if p == 1.0 else math.copysign(abs(x) ** p, x)
