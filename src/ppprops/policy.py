"""The linear policy u = W^T s + b and its one flat parameter layout.

Layout of theta (length D = (n_s + 1) * n_a), row-major over W then the bias:

    theta[i * n_a + j]      = W[i, j]   for observation i in [0, n_s), action j in [0, n_a)
    theta[n_s * n_a + j]    = b[j]

So action j's score is  u_j = sum_i s_i * theta[i * n_a + j] + theta[n_s * n_a + j].
Every prompt describes this same layout (see ``ppprops.wire.layout``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import ConfigError

FloatArray = NDArray[np.float64]


def param_count(n_s: int, n_a: int) -> int:
    """D = (n_s + 1) n_a: the weights W (n_s x n_a) and the bias b (n_a) of u = W^T s + b (paper Eq. 10, Sec. III)."""
    return (n_s + 1) * n_a


@dataclass(frozen=True)
class LinearPolicy:
    """A deployable linear controller: continuous actions are clipped, discrete ones take the argmax."""

    W: FloatArray  # shape (n_s, n_a)
    b: FloatArray  # shape (n_a,)
    discrete: bool
    low: FloatArray | None = None  # action bounds for continuous control
    high: FloatArray | None = None

    @classmethod
    def from_flat(
        cls,
        theta: NDArray[np.floating],
        n_s: int,
        n_a: int,
        *,
        discrete: bool,
        low: NDArray[np.floating] | None = None,
        high: NDArray[np.floating] | None = None,
    ) -> LinearPolicy:
        """The policy of a flat theta of shape ((n_s + 1) n_a,) in the module's layout.

        ``low``/``high``: continuous action bounds, shape (n_a,). Raises ConfigError for a theta
        of another length.
        """
        theta64: NDArray[np.float64] = np.asarray(theta, dtype=np.float64)
        if theta64.shape != (param_count(n_s, n_a),):
            raise ConfigError(
                f"policy needs {param_count(n_s, n_a)} parameters for n_s={n_s}, n_a={n_a}, got shape {theta64.shape}"
            )
        W = theta64[: n_s * n_a].reshape(n_s, n_a).copy()
        b = theta64[n_s * n_a :].copy()
        lo = None if low is None else np.asarray(low, dtype=np.float64)
        hi = None if high is None else np.asarray(high, dtype=np.float64)
        return cls(W=W, b=b, discrete=discrete, low=lo, high=hi)

    @property
    def n_s(self) -> int:
        """Length of the state vector s."""
        return int(self.W.shape[0])

    @property
    def n_a(self) -> int:
        """Number of action scores (discrete actions, or continuous action dimensions)."""
        return int(self.W.shape[1])

    def flat(self) -> FloatArray:
        """theta in the one flat layout (module docstring), shape ((n_s + 1) n_a,); inverse of ``from_flat``."""
        return np.concatenate([self.W.reshape(-1), self.b])

    def scores(self, s: NDArray[np.floating]) -> FloatArray:
        """u = W^T s + b for a state ``s`` of shape (n_s,); shape (n_a,)."""
        return np.asarray(s, dtype=np.float64) @ self.W + self.b

    def act(self, s: NDArray[np.floating]) -> int | FloatArray:
        """The action for state ``s`` (shape (n_s,)): argmax of u (discrete), or u clipped to [low, high]."""
        u = self.scores(s)
        if self.discrete:
            return int(np.argmax(u))
        if self.low is not None and self.high is not None:
            return np.clip(u, self.low, self.high)
        return u
