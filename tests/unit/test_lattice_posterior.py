"""The exact likelihood of integer returns through the warped, dithered reward map
(``simfit.lattice_posterior``, the ``sim-marginal-lattice`` attack's reading): planted maps are
read back, from printed returns made as the codec makes them (y = c (w_p(r + d) - w_p(s)))."""

from __future__ import annotations

import numpy as np
import pytest

from ppprops.privacy.simfit import RewardPrior, lattice_posterior


def _printed(r: np.ndarray, c: float, s: float, p: float, rng: np.random.Generator) -> np.ndarray:
    w = lambda x: np.sign(x) * np.abs(x) ** p  # noqa: E731
    d = rng.uniform(-0.5, 0.5, size=len(r))  # the dither: below half a step of the integer lattice
    return c * (w(r + d) - w(s))


@pytest.mark.parametrize(("c", "s", "p", "returns"), [
    (2.0, -100.0, 1.5, "cartpole"),  # episode lengths 9..500, rewards stretched
    (0.3, 250.0, 0.6, "cartpole"),  # compressed, origin inside the range
    (5.0, 120.0, 1.3, "acrobot"),  # negative returns -500..-60
])
def test_a_planted_map_is_read_back_when_the_raw_returns_are_known_to_the_simulation(c: float, s: float, p: float,
                                                                                      returns: str) -> None:
    rng = np.random.default_rng(3)
    r = (rng.choice(np.arange(9, 501), size=20, replace=False) if returns == "cartpole"
         else -rng.choice(np.arange(60, 501), size=20, replace=False)).astype(float)
    y = _printed(r, c, s, p, rng)
    R = np.repeat(r[:, None], 64, axis=1)  # each policy's simulated episodes all end at its raw return
    c_hat, s_hat, p_hat = lattice_posterior(R, y, 1.0, RewardPrior(S=500.0))
    # the grid bounds the precision when the raw returns are pinned: p in steps of 1.2%, which at
    # |r| = 500 moves c by about 10% (c |r|^p held); s in steps of 5
    assert c_hat == pytest.approx(c, rel=0.15) and p_hat == pytest.approx(p, rel=0.03) and s_hat == pytest.approx(s, abs=25.0)
    assert abs(np.log(c_hat / c)) < abs(np.log(1.0 / c)) / 4  # far closer than the prior's guess c = 1

