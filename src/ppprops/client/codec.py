"""The only producer of wire values: encodes raw candidates into what the LLM may see, decodes answers.

The paper's maps (Sec. II-B, II-C) are theta~ = A theta and r~ = c r. The hardening switches of
``ppprops.methods`` extend them (docs/threat-model.md):

- secret offsets: theta~ = A (theta - m), r~ = c (r - s);
- warped parameters: theta~ = A (T(theta) - T(m)), where T maps the open public box onto the
  whole real line (T(u) = W/pi tan(pi (u - lo)/W - pi/2), slope 1 at the centre). Every encoded
  value decodes strictly inside the box, so no answer is ever clipped, and encoded values are
  clamped to +-ENCODED_LIMIT, a public bound, so an extreme answer never echoes back a secret;
- warped rewards: r~ = c (w_p(r) - w_p(s)), w_p(x) = sign(x) |x|^p, an increasing map (ranking
  kept) whose differences are not multiples of one constant.
Every map is increasing in each coordinate, so larger encoded values still mean larger raw ones.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from ..evaluation import Feedback
from ..wire.encoded import EncodedEntry
from .secrets import Secrets

ENCODED_LIMIT = 1.0e6  # public clamp of warped encoded parameters (answers beyond it decode as if at it)


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
    ) -> None:
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
        if self.warp_params:
            if box is None:
                raise ValueError("warped parameters need the public box")
            self._lo, self._hi = float(box[0]), float(box[1])
            self._m_t = self._t(self._m)

    def __repr__(self) -> str:
        return (f"Codec(encode_params={self.encode_params}, scale_rewards={self.scale_rewards}, offsets={self.offsets}, "
                f"warp_params={self.warp_params}, warp_rewards={self.warp_rewards})")

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
        x = np.asarray(theta, dtype=np.float64)
        if self.warp_params:
            return np.clip(self._a * (self._t(x) - self._m_t), -ENCODED_LIMIT, ENCODED_LIMIT)
        return self._a * (x - self._m)

    def decode(self, theta_enc: NDArray[np.floating]) -> NDArray[np.float64]:
        x = np.asarray(theta_enc, dtype=np.float64)
        if self.warp_params:
            return self._t_inv(np.clip(x, -ENCODED_LIMIT, ENCODED_LIMIT) / self._a + self._m_t)
        return x / self._a + self._m

    # -- rewards --------------------------------------------------------------------------
    def _w(self, r: float) -> float:
        return r if self._p == 1.0 else math.copysign(abs(r) ** self._p, r)

    def scale(self, r: float) -> float:
        """Encode one reward-valued number (a return, a component, the optimum when disclosed)."""
        r = float(r)
        if self._p == 1.0:
            return self._c * (r - self._s)
        return self._c * (self._w(r) - self._w(self._s))

    def scale_components(self, components: Mapping[str, float]) -> dict[str, float]:
        return {k: self.scale(v) for k, v in components.items()}

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
        episode_returns=tuple(codec.scale(r) for r in fb.episode_returns),
    )
