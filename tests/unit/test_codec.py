import json
import os
import stat

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ppprops.client.codec import Codec, encode_feedback
from ppprops.client.secrets import Secrets
from ppprops.errors import KeyFileError
from ppprops.evaluation import Feedback

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


def _secrets(D: int, seed: int) -> Secrets:
    rng = np.random.default_rng(seed)
    return Secrets(run_id="r", a=np.exp(rng.uniform(np.log(0.1), np.log(10), D)), c=float(np.exp(rng.uniform(-2.3, 2.3))))


@settings(max_examples=200, deadline=None)
@given(st.lists(finite, min_size=1, max_size=40), st.integers(0, 2**32 - 1))
def test_parameter_round_trip(theta: list[float], seed: int) -> None:
    codec = Codec(_secrets(len(theta), seed), encode_params=True, scale_rewards=True)
    x = np.array(theta)
    np.testing.assert_allclose(codec.decode(codec.encode(x)), x, rtol=1e-12, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.lists(finite, min_size=2, max_size=30), st.integers(0, 2**32 - 1))
def test_reward_scaling_preserves_ranking(returns: list[float], seed: int) -> None:
    codec = Codec(_secrets(3, seed), encode_params=True, scale_rewards=True)
    scaled = [codec.scale(r) for r in returns]
    for i in range(len(returns)):
        for j in range(len(returns)):
            if returns[i] < returns[j]:
                # rounding is monotone, so order never flips; a gap above rounding error stays strict
                assert scaled[i] <= scaled[j]
                if returns[j] - returns[i] > 1e-9 * max(1.0, abs(returns[i]), abs(returns[j])):
                    assert scaled[i] < scaled[j]
            if returns[i] == returns[j]:
                assert scaled[i] == scaled[j]


def test_components_scaled_diagnostics_not() -> None:
    s = _secrets(2, 0)
    fb = Feedback(
        ret=10.0, components={"forward": 4.0, "ctrl": -1.0}, diagnostics={"episode_length": 50.0, "termination": "pole_fell"}, episode_returns=(10.0,)
    )
    enc = encode_feedback(Codec(s, encode_params=True, scale_rewards=True), fb)
    assert enc.ret == pytest.approx(s.c * 10.0)
    assert enc.components == pytest.approx({"forward": s.c * 4.0, "ctrl": -s.c})
    assert enc.diagnostics == fb.diagnostics
    assert enc.episode_returns == pytest.approx((s.c * 10.0,))


def test_switched_off_mechanisms_are_identity() -> None:
    s = _secrets(3, 1)
    codec = Codec(s, encode_params=False, scale_rewards=False)
    np.testing.assert_array_equal(codec.encode(np.array([1.0, -2.0, 3.0])), [1.0, -2.0, 3.0])
    assert codec.scale(7.5) == 7.5


@pytest.mark.parametrize("theta", [2.0, [1.0, 2.0], [[1.0, 2.0, 3.0]], [1.0, 2.0, 3.0, 4.0]])
@pytest.mark.parametrize("encode_params", [True, False])
def test_encode_refuses_a_vector_of_another_shape(theta: object, encode_params: bool) -> None:
    """A scalar or a vector of the wrong length is an error, never broadcast into D encoded values."""
    codec = Codec(_secrets(3, 1), encode_params=encode_params, scale_rewards=True)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        codec.encode(np.asarray(theta))


def test_secrets_are_fresh_positive_and_in_documented_range() -> None:
    a = Secrets.generate("x", 500)
    b = Secrets.generate("x", 500)
    assert not np.allclose(a.a, b.a) and a.c != b.c
    for s in (a, b):
        assert np.all(s.a >= 0.1) and np.all(s.a <= 10.0) and 0.1 <= s.c <= 10.0


def test_key_file_is_0600_and_round_trips(tmp_path) -> None:  # type: ignore[no-untyped-def]
    s = Secrets.generate("run-1", 10)
    path = tmp_path / "secrets.key"
    s.save(path)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    back = Secrets.load(path, run_id="run-1", D=10, fingerprint=s.fingerprint())
    np.testing.assert_array_equal(back.a, s.a)
    assert back.c == s.c


def test_secret_values_never_appear_in_repr() -> None:
    s = Secrets.generate("run-1", 4)
    text = repr(s) + str(s) + repr(Codec(s, encode_params=True, scale_rewards=True))
    assert "hidden" in text
    for v in [*s.a, s.c]:
        assert f"{v:.4f}" not in text and repr(float(v)) not in text


@pytest.mark.parametrize(
    "content,run_id,match",
    [
        (None, "run-1", "missing"),
        ("not json", "run-1", "corrupt"),
        (json.dumps({"format": "ppprops.secrets/1", "run_id": "run-1", "a": [1, 2], "c": 1.0}), "run-1", "out of range"),
        (json.dumps({"format": "ppprops.secrets/1", "run_id": "run-1", "a": [1, 2, -3], "c": 1.0}), "run-1", "out of range"),
        (json.dumps({"format": "other", "run_id": "run-1", "a": [1, 2, 3], "c": 1.0}), "run-1", "corrupt"),
        (json.dumps({"format": "ppprops.secrets/1", "run_id": "run-2", "a": [1, 2, 3], "c": 1.0}), "run-1", "belongs to run run-2"),
    ],
)
def test_bad_key_files_are_clear_errors(tmp_path, content, run_id, match) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "secrets.key"
    if content is not None:
        path.write_text(content)
    with pytest.raises(KeyFileError, match=match):
        Secrets.load(path, run_id=run_id, D=3)


def test_key_with_wrong_fingerprint_is_refused(tmp_path) -> None:  # type: ignore[no-untyped-def]
    s = Secrets.generate("run-1", 3)
    s.save(tmp_path / "k")
    with pytest.raises(KeyFileError, match="does not match"):
        Secrets.load(tmp_path / "k", run_id="run-1", D=3, fingerprint="0" * 64)
