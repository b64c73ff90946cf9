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


def test_flat_layout_on_a_written_out_example() -> None:
    """n_s = 2, n_a = 3: theta = [W00 W01 W02 W10 W11 W12 b0 b1 b2] (row-major W, then b)."""
    pol = LinearPolicy.from_flat(np.arange(9.0), 2, 3, discrete=True)
    np.testing.assert_array_equal(pol.W, [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    np.testing.assert_array_equal(pol.b, [6.0, 7.0, 8.0])
    assert [layout.param_index(i, j, 3) for i in range(2) for j in range(3)] == [0, 1, 2, 3, 4, 5]
    assert [layout.bias_index(j, 2, 3) for j in range(3)] == [6, 7, 8]


@pytest.mark.parametrize("n_s,n_a", [(3, 2), (1, 1), (5, 4)])
def test_scores_follow_the_flat_layout(n_s: int, n_a: int) -> None:
    """u_j = sum_i s_i theta[i n_a + j] + theta[n_s n_a + j], summed here term by term from theta
    (not from the policy's W and b), so a layout error in from_flat or scores fails."""
    rng = np.random.default_rng(n_s * 10 + n_a)
    theta = rng.normal(size=param_count(n_s, n_a))
    s = rng.normal(size=n_s)
    expected = [sum(s[i] * theta[i * n_a + j] for i in range(n_s)) + theta[n_s * n_a + j] for j in range(n_a)]
    pol = LinearPolicy.from_flat(theta, n_s, n_a, discrete=True)
    np.testing.assert_allclose(pol.scores(s), expected, rtol=1e-12, atol=1e-12)
    assert pol.act(s) == int(np.argmax(expected))


def test_discrete_takes_argmax_and_continuous_clips() -> None:
    theta = np.array([1.0, -1.0, 0.0, 0.0])  # n_s=1, n_a=2
    assert LinearPolicy.from_flat(theta, 1, 2, discrete=True).act(np.array([2.0])) == 0
    assert LinearPolicy.from_flat(theta, 1, 2, discrete=True).act(np.array([-2.0])) == 1
    cont = LinearPolicy.from_flat(theta, 1, 2, discrete=False, low=np.array([-0.5, -0.5]), high=np.array([0.5, 0.5]))
    np.testing.assert_array_equal(cont.act(np.array([3.0])), [0.5, -0.5])


def test_wrong_length_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="needs 10 parameters"):
        LinearPolicy.from_flat(np.zeros(9), 4, 2, discrete=True)
