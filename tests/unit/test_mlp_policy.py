"""MLP policies: the forward pass, the parameter order, the layer boxes, the keyed warm-up, the
structure the chat prompt describes, and the one line each bad input gets."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.client.hardening import generate_secrets
from ppprops.errors import ConfigError
from ppprops.policy import LINEAR, LinearPolicy, MLPPolicy, PolicySpec, make_network, parse_policy
from ppprops.settings import build_config
from ppprops.study import Study
from ppprops.tasks import load_task
from ppprops.tasks.options import TaskOptions
from ppprops.wire import layout


def test_the_forward_pass_is_the_hand_computation() -> None:
    # n_s = 2, one hidden layer of 2 tanh units, n_a = 1: W1 = [[1, -2], [0.5, 3]], b1 = [0.1, -0.2], W2 = [[2], [-1]], b2 = [0.3]
    spec = PolicySpec(kind="mlp", hidden=(2,))
    theta = np.array([1.0, -2.0, 0.5, 3.0, 0.1, -0.2, 2.0, -1.0, 0.3])
    s = np.array([0.4, -0.6])
    h0 = math.tanh(0.4 * 1.0 + (-0.6) * 0.5 + 0.1)  # tanh(0.2)
    h1 = math.tanh(0.4 * -2.0 + (-0.6) * 3.0 - 0.2)  # tanh(-2.8)
    u = 2.0 * h0 - 1.0 * h1 + 0.3
    net = MLPPolicy.from_flat(theta, spec, 2, 1, discrete=False, low=np.array([-2.0]), high=np.array([2.0]))
    assert net.scores(s)[0] == pytest.approx(u, abs=1e-12)
    assert net.act(s)[0] == pytest.approx(min(u, 2.0), abs=1e-12)
    relu = MLPPolicy.from_flat(theta, spec.model_copy(update={"activation": "relu"}), 2, 1, discrete=True)
    assert relu.scores(s)[0] == pytest.approx(2.0 * 0.2 - 1.0 * 0.0 + 0.3, abs=1e-12)  # relu(0.2) = 0.2, relu(-2.8) = 0


def test_the_parameter_order_is_each_layer_weights_row_by_row_then_its_bias() -> None:
    spec = parse_policy("mlp:3,2")
    n_s, n_a = 2, 2
    assert spec.layer_shapes(n_s, n_a) == [(2, 3), (3, 2), (2, 2)]
    D = spec.param_count(n_s, n_a)
    assert D == (2 + 1) * 3 + (3 + 1) * 2 + (2 + 1) * 2 == 23
    net = MLPPolicy.from_flat(np.arange(D, dtype=float), spec, n_s, n_a, discrete=True)
    (W1, b1), (W2, b2), (W3, b3) = net.layers
    assert W1.tolist() == [[0, 1, 2], [3, 4, 5]] and b1.tolist() == [6, 7, 8]
    assert W2.tolist() == [[9, 10], [11, 12], [13, 14]] and b2.tolist() == [15, 16]
    assert W3.tolist() == [[17, 18], [19, 20]] and b3.tolist() == [21, 22]
    assert np.array_equal(net.flat(), np.arange(D))
    # the prompt's words name the same indices (wire side, no import of ppprops.policy)
    words = layout.describe_layers((2, 3, 2, 2))
    assert "params has 23 entries" in words
    assert "params[0..5] form the 2x3 matrix W1 row by row (W1[i][j] = params[0 + i*3 + j]), params[6..8] are the 3 biases b1" in words
    assert "params[17..20] form the 2x2 matrix W3 row by row (W3[i][j] = params[17 + i*2 + j]), params[21..22] are the 2 biases b3" in words
    # the linear family is the one-layer case, in the paper's layout
    theta = np.arange(LINEAR.param_count(3, 2), dtype=float)
    lin = make_network(theta, LINEAR, 3, 2, discrete=True)
    assert isinstance(lin, LinearPolicy) and lin.W.tolist() == [[0, 1], [2, 3], [4, 5]] and lin.b.tolist() == [6, 7]


def test_d_follows_the_policy_for_a_gym_id_and_a_paper_task() -> None:
    assert load_task("Pendulum-v1").D == 4
    pend = load_task(options=TaskOptions(env="Pendulum-v1", policy="mlp:16"))
    assert pend.D == (3 + 1) * 16 + (16 + 1) * 1 == 81
    cart = load_task(options=TaskOptions(env="CartPole", policy={"kind": "mlp", "hidden": [8, 8]}, activation="relu"))
    assert cart.name == "CartPole" and cart.D == 5 * 8 + 9 * 8 + 9 * 2 and cart.policy.activation == "relu"
    assert cart.spec.model_dump(mode="json")["policy"] == {"kind": "mlp", "hidden": [8, 8], "activation": "relu"}
    assert "policy" not in load_task("CartPole").spec.model_dump(mode="json")  # a linear declaration is stored as before


def test_each_layer_has_its_box_and_the_warm_up_a_scaled_initialisation() -> None:
    spec = parse_policy("mlp:16")
    boxes = spec.layer_boxes(3, 1, (-6.0, 6.0))
    assert boxes == [pytest.approx((-6 / math.sqrt(3), 6 / math.sqrt(3))), pytest.approx((-1.5, 1.5))]
    lo, hi = spec.bounds(3, 1, (-6.0, 6.0))
    assert lo.shape == (81,) and np.allclose(hi[:64], 6 / math.sqrt(3)) and np.allclose(hi[64:], 1.5) and np.array_equal(lo, -hi)
    ilo, ihi = spec.init_bounds(3, 1, (-6.0, 6.0))
    assert np.allclose(ihi[:64], 1 / math.sqrt(3)) and np.allclose(ihi[64:], 0.25) and np.array_equal(ilo, -ihi)
    assert LINEAR.layer_boxes(3, 1, (-6.0, 6.0)) == [(-6.0, 6.0)]


def _study(tmp_path: Path, name: str, key: int, method: str = "random") -> Study:
    task = load_task(options=TaskOptions(env="Pendulum-v1", policy="mlp:4"))
    config = build_config({"method": method, "warmup": 3, "iterations": 2, "seed": 5, "final_episodes": 1}, task=task)
    secrets = generate_secrets(f"mlp-{key}", task, config.encoding, rng=np.random.default_rng(key))
    return Study.create(config, tmp_path / name, secrets=secrets)


def test_the_warm_up_is_keyed_by_the_secrets_and_drawn_from_the_layers_initialisation(tmp_path: Path) -> None:
    with _study(tmp_path, "a", 1) as a, _study(tmp_path, "b", 1) as b, _study(tmp_path, "c", 2) as c:
        ta, tb, tc = a.ask(), b.ask(), c.ask()
        assert ta.source == "warmup" and len(ta.theta) == 4 * 4 + 5 * 1 == 21
        assert np.array_equal(ta.theta, tb.theta)  # same secrets and run seed: the same draw
        assert not np.allclose(ta.theta, tc.theta)  # same run seed, other secrets: another draw
        lo, hi = a.task.policy.init_bounds(3, 1, (-6.0, 6.0))
        for t in (ta, tc):
            assert np.all(t.theta >= lo) and np.all(t.theta <= hi)
        (W1, b1), (W2, b2) = ta.layers
        assert W1.shape == (3, 4) and b1.shape == (4,) and W2.shape == (4, 1) and b2.shape == (1,)
        assert np.array_equal(np.concatenate([W1.ravel(), b1, W2.ravel(), b2]), ta.theta)
        doc = ta.to_json()
        assert "W" not in doc and [np.asarray(layer["W"]).shape for layer in doc["layers"]] == [(3, 4), (4, 1)]
        with pytest.raises(AttributeError, match="mlp:4 .tanh. policy: it has layers"):
            _ = ta.W


def test_the_chat_prompt_describes_the_layers_from_public_values_only() -> None:
    from ppprops.wire.encoded import PromptContext
    from ppprops.wire.prompt import parameters_section

    ctx = PromptContext(summary="", observations=(("x", "a"), ("y", "b"), ("v", "c")), actions=("torque",), discrete=False,
                        reward_text="", hints="", encoded_params=True, scaled_rewards=True, detailed_feedback=False,
                        param_range=None, optimum=None, hidden=(16,), activation="tanh")  # fmt: skip
    assert ctx.D == 81
    text = parameters_section(ctx)
    assert text.startswith("The policy is a neural network (a multilayer perceptron) with 2 layers: "
                           "h1[j] = tanh(sum_i s[i]*W1[i][j] + b1[j]) for its 16 hidden units; the output u[j] = sum_i h1[i]*W2[i][j] + b2[j].")
    assert "params[0..47] form the 3x16 matrix W1" in text and "params[80..80] are the 1 biases b2" in text
    assert "linear" not in text and "encoded coordinate system" in text
    raw = parameters_section(PromptContext(**{**ctx.__dict__, "encoded_params": False, "layer_ranges": ((-3.46, 3.46), (-1.5, 1.5))}))
    assert raw.endswith("The parameters of each layer must lie in its own range: layer 1 (W1, b1) in [-3.46, 3.46], layer 2 (W2, b2) in [-1.50, 1.50].")


@pytest.mark.parametrize("argv,line", [
    (["run", "--env", "Pendulum-v1", "--policy", "mlp:0"],
     "ppprops: error: argument --policy: policy 'mlp:0': hidden sizes must be whole numbers in [1, 4096], got '0'"),
    (["run", "--env", "Pendulum-v1", "--policy", "mlp:16,x"],
     "ppprops: error: argument --policy: policy 'mlp:16,x': hidden sizes must be whole numbers in [1, 4096], got 'x'"),
    (["run", "--env", "Pendulum-v1", "--policy", "cnn:3"],
     "ppprops: error: argument --policy: policy must be linear or mlp:H1[,H2,...] (hidden sizes), got 'cnn:3'"),
    (["run", "--env", "Pendulum-v1", "--policy", "mlp:16", "--activation", "sigmoid"],
     "ppprops: error: argument --activation: invalid choice: 'sigmoid' (choose from 'tanh', 'relu')"),
])  # fmt: skip
def test_a_bad_policy_flag_is_one_line_and_exit_2(argv: list[str], line: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert capsys.readouterr().err == line + "\n"


@pytest.mark.parametrize("argv,line", [
    (["run", "--env", "Pendulum-v1", "--activation", "relu"],
     "ppprops: error: --activation applies to an mlp policy (--policy mlp:...), not to the linear one"),
    (["run", "--env", "Pendulum-v1", "--policy", "mlp:256,256"],
     "ppprops: error: --policy mlp:256,256 is too large for the endpoint's context: D = 67073 parameters, so one answer needs about "
     "793790 tokens and the prompt's history at least as many (1587580 in all), more than the embedded model's context of 16384 "
     "tokens (--context-size): use fewer hidden units"),
    (["run", "--env", "CartPole", "--policy", "mlp:8", "--method", "r2po", "--base-url", "http://127.0.0.1:9/v1", "--model", "m"],
     "ppprops: error: --method r2po searches the linear policy only (its critic reads a linear rollout): --policy mlp:8 needs "
     "--method pp, random or cmaes"),
])  # fmt: skip
def test_a_bad_policy_setting_is_one_line_and_exit_2_before_any_request(argv: list[str], line: str, tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    out = tmp_path / "run"
    assert main([*argv, "--out", str(out)]) == 2
    assert capsys.readouterr().err == line + "\n"
    assert not out.exists()  # refused before the run directory is made


def test_a_task_files_policy_table_is_read_and_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = tmp_path / "pend.toml"
    good.write_text('name = "Pend"\nenv = "Pendulum-v1"\n[policy]\nkind = "mlp"\nhidden = [8]\nactivation = "relu"\n')
    task = load_task(good)
    assert task.policy == PolicySpec(kind="mlp", hidden=(8,), activation="relu") and task.D == 4 * 8 + 9 * 1
    assert load_task(options=TaskOptions(task_file=good, policy="mlp:4")).D == 4 * 4 + 5  # the flag wins
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "Bad"\nenv = "Pendulum-v1"\n[policy]\nkind = "mlp"\nhidden = [8]\nactivation = "swish"\n')
    with pytest.raises(ConfigError, match=r"^task file .*bad.toml: policy activation must be one of tanh, relu, got 'swish'$"):
        load_task(bad)
    assert main(["task", "check", str(good)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "  policy mlp:8 (relu): D = 41 parameters (3 observations, 1 actions)"
