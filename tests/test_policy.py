import numpy as np
import pytest

from ppprops.errors import ConfigError
from ppprops.policy import LinearPolicy, param_count
from ppprops.wire import layout


@pytest.mark.parametrize("n_s,n_a", [(4, 2), (6, 3), (27, 8)])
def test_flat_layout_matches_the_prompt_description(n_s: int, n_a: int) -> None:
    theta = np.arange(param_count(n_s, n_a), dtype=float)
    pol = LinearPolicy.from_flat(theta, n_s, n_a, discrete=True)
    for i in range(n_s):
        for j in range(n_a):
            assert pol.W[i, j] == theta[layout.param_index(i, j, n_a)]
    for j in range(n_a):
        assert pol.b[j] == theta[layout.bias_index(j, n_s, n_a)]
    np.testing.assert_array_equal(pol.flat(), theta)
    text = layout.describe(n_s, n_a)
    assert f"params[{n_s * n_a}..{(n_s + 1) * n_a - 1}]" in text
    assert f"W[i][j] = params[i*{n_a} + j]" in text


def test_scores_are_w_transpose_s_plus_b() -> None:
    rng = np.random.default_rng(1)
    theta = rng.normal(size=param_count(3, 2))
    pol = LinearPolicy.from_flat(theta, 3, 2, discrete=True)
    s = rng.normal(size=3)
    np.testing.assert_allclose(pol.scores(s), pol.W.T @ s + pol.b)


def test_discrete_takes_argmax_and_continuous_clips() -> None:
    theta = np.array([1.0, -1.0, 0.0, 0.0])  # n_s=1, n_a=2
    assert LinearPolicy.from_flat(theta, 1, 2, discrete=True).act(np.array([2.0])) == 0
    assert LinearPolicy.from_flat(theta, 1, 2, discrete=True).act(np.array([-2.0])) == 1
    cont = LinearPolicy.from_flat(theta, 1, 2, discrete=False, low=np.array([-0.5, -0.5]), high=np.array([0.5, 0.5]))
    np.testing.assert_array_equal(cont.act(np.array([3.0])), [0.5, -0.5])


def test_wrong_length_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="needs 10 parameters"):
        LinearPolicy.from_flat(np.zeros(9), 4, 2, discrete=True)
