"""The only producer of wire values: encodes raw candidates into what the LLM may see, decodes answers."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from ..evaluation import Feedback
from ..wire.encoded import EncodedEntry
from .secrets import Secrets


class Codec:
    """theta~ = A theta and r~ = c r, each switched on by its own setting (identity when off)."""

    def __init__(self, secrets: Secrets, *, encode_params: bool, scale_rewards: bool) -> None:
        self._a = np.asarray(secrets.a, dtype=np.float64) if encode_params else np.ones(len(secrets.a))
        self._c = float(secrets.c) if scale_rewards else 1.0
        self.encode_params = encode_params
        self.scale_rewards = scale_rewards

    def __repr__(self) -> str:
        return f"Codec(encode_params={self.encode_params}, scale_rewards={self.scale_rewards})"

    def encode(self, theta: NDArray[np.floating]) -> NDArray[np.float64]:
        return self._a * np.asarray(theta, dtype=np.float64)

    def decode(self, theta_enc: NDArray[np.floating]) -> NDArray[np.float64]:
        return np.asarray(theta_enc, dtype=np.float64) / self._a

    def scale(self, r: float) -> float:
        return self._c * float(r)

    def scale_components(self, components: Mapping[str, float]) -> dict[str, float]:
        return {k: self._c * float(v) for k, v in components.items()}

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
            diagnostics=tuple((k, v) for k, v in diagnostics.items()),
        )


def encode_feedback(codec: Codec, fb: Feedback) -> Feedback:
    """Scale every reward-valued field by c; diagnostics are not rewards and stay as they are."""
    return Feedback(
        ret=codec.scale(fb.ret),
        components=codec.scale_components(fb.components),
        diagnostics=dict(fb.diagnostics),
        episode_returns=tuple(codec.scale(r) for r in fb.episode_returns),
    )
