"""pp-hardened: the paper's presets stay as they were, the new secrets load alongside old key files,
and the hardened codec, warm-up and wording hide what the paper's scheme lets through."""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ppprops.client.codec import ENCODED_LIMIT, Codec, encode_feedback
from ppprops.client.context import prompt_context
from ppprops.client.hardening import codec_for, generate_secrets
from ppprops.client.secrets import Secrets
from ppprops.errors import ConfigError, KeyFileError
from ppprops.evaluation import Feedback
from ppprops.methods import PRESETS, Mechanisms, resolve
from ppprops.proposers.uniform import warmup_sampler
from ppprops.seeding import Streams
from ppprops.tasks import get_task
from ppprops.wire import build_prompt

from support import make_config

BOX = (-6.0, 6.0)


def _hardened(D: int, seed: int) -> Secrets:
    rng = np.random.default_rng(seed)
    return Secrets(run_id="h", a=np.exp(rng.uniform(np.log(1 / 3), np.log(3), D)), c=float(np.exp(rng.uniform(-2.3, 2.3))),
                   m=rng.uniform(-3, 3, D), s=float(rng.uniform(-500, 500)), p=float(rng.choice([0.6, 1.7])))


def _codec(secrets: Secrets) -> Codec:
    return Codec(secrets, encode_params=True, scale_rewards=True, offsets=True, warp_params=True, warp_rewards=True, box=BOX,
                 hidden_diagnostics=frozenset({"episode_length"}))


def test_paper_presets_are_unchanged_and_every_hardening_switch_is_off_in_them() -> None:
    expected = {
        "vanilla": (False, False, False, True, True),
        "pe": (True, False, False, True, True),
        "df": (False, False, True, True, True),
        "pp": (True, True, True, False, False),
    }
    for name, five in expected.items():
        m = PRESETS[name]
        assert (m.encode_params, m.scale_rewards, m.detailed_feedback, m.disclose_optimum, m.disclose_reward_structure) == five
        assert not m.hardened
    h = PRESETS["pp-hardened"]
    assert h.hardened and all(h.to_json().values()) is False  # optimum and reward structure stay withheld
    assert h.secret_offsets and h.warp_params and h.warp_rewards and h.hide_return_diagnostics and h.encoded_warmup


def test_configs_stored_before_the_switches_existed_still_load() -> None:
    old = {"encode_params": True, "scale_rewards": True, "detailed_feedback": True, "disclose_optimum": False,
           "disclose_reward_structure": False}
    assert Mechanisms.from_json(old) == PRESETS["pp"]
    with pytest.raises(KeyError):
        Mechanisms.from_json({"encode_params": True})


@pytest.mark.parametrize("overrides", [dict(encoded_warmup=True), dict(warp_params=True, encode_params=False),
                                       dict(warp_rewards=True, scale_rewards=False)])
def test_combinations_that_would_reveal_a_secret_are_refused(overrides: dict[str, bool]) -> None:
    with pytest.raises(ConfigError):
        resolve("pp", **overrides)


def test_old_key_files_load_and_keep_their_fingerprint(tmp_path: Path) -> None:
    a, c = [0.5, 2.0, 3.0], 1.5
    payload = {"format": "ppprops.secrets/1", "run_id": "old", "a": a, "c": c}
    (tmp_path / "k").write_text(json.dumps(payload))
    fp = hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()
    s = Secrets.load(tmp_path / "k", run_id="old", D=3, fingerprint=fp)
    assert s.m is None and s.s is None and s.p is None and not s.has_extras
    assert s.origin.tolist() == [0, 0, 0] and s.reward_origin == 0 and s.exponent == 1
    # the paper codec is exactly theta~ = A theta, r~ = c r for such a key
    codec = Codec(s, encode_params=True, scale_rewards=True, offsets=True, warp_rewards=True)
    np.testing.assert_array_equal(codec.encode(np.array([1.0, -2.0, 0.5])), np.array(a) * [1.0, -2.0, 0.5])
    assert codec.scale(7.0) == c * 7.0


def test_hardened_key_files_round_trip_and_reject_bad_extras(tmp_path: Path) -> None:
    s = Secrets.generate_hardened("h", 5, box=BOX, reward_scale=500.0)
    s.save(tmp_path / "k")
    back = Secrets.load(tmp_path / "k", run_id="h", D=5, fingerprint=s.fingerprint())
    assert np.array_equal(back.m, s.m) and back.s == s.s and back.p == s.p and "hardened" in repr(back)
    assert str(s.s) not in repr(back)
    for bad in ({"p": -1.0}, {"m": [0.0]}, {"s": "x"}):
        doc = json.loads((tmp_path / "k").read_text()) | bad
        (tmp_path / "bad").write_text(json.dumps(doc))
        with pytest.raises(KeyFileError):
            Secrets.load(tmp_path / "bad", run_id="h", D=5)


def test_hardened_secret_distribution() -> None:
    draws = [Secrets.generate_hardened("h", 50, box=BOX, reward_scale=500.0) for _ in range(40)]
    a = np.concatenate([d.a for d in draws])
    p = np.array([d.p for d in draws])
    assert a.min() >= 1 / 3 and a.max() <= 3 and abs(np.median(np.log(a))) < 0.2
    assert np.all((np.abs(np.log(p)) >= math.log(1.25)) & (np.abs(np.log(p)) <= math.log(2)))
    assert (p > 1).any() and (p < 1).any()
    m = np.concatenate([d.m for d in draws])
    assert m.min() >= -3 and m.max() <= 3
    assert all(abs(d.s) <= 500 for d in draws)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-5.99, 5.99), min_size=1, max_size=20), st.integers(0, 2**31))
def test_warped_parameters_round_trip_inside_the_box(theta: list[float], seed: int) -> None:
    codec = _codec(_hardened(len(theta), seed))
    x = np.array(theta)
    np.testing.assert_allclose(codec.decode(codec.encode(x)), x, rtol=1e-9, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e9, 1e9), min_size=1, max_size=20), st.integers(0, 2**31))
def test_any_encoded_answer_decodes_strictly_inside_the_box_and_echoes_back_publicly(x: list[float], seed: int) -> None:
    codec = _codec(_hardened(len(x), seed))
    theta = codec.decode(np.array(x))
    assert np.all(theta > BOX[0]) and np.all(theta < BOX[1])  # nothing is ever clipped, so no box edge is echoed
    np.testing.assert_allclose(codec.encode(theta), np.clip(x, -ENCODED_LIMIT, ENCODED_LIMIT), rtol=1e-6, atol=1e-6)


def test_box_edges_encode_to_the_public_clamp_not_to_a_secret() -> None:
    codec = _codec(_hardened(4, 0))
    assert codec.encode(np.array([6.0, -6.0, 6.0, -6.0])).tolist() == [ENCODED_LIMIT, -ENCODED_LIMIT] * 2


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4), min_size=2, max_size=30), st.integers(0, 2**31))
def test_warped_rewards_keep_the_ranking_and_ties(returns: list[float], seed: int) -> None:
    codec = _codec(_hardened(2, seed))
    enc = [codec.scale(r) for r in returns]
    for i, ri in enumerate(returns):
        for j, rj in enumerate(returns):
            if ri < rj:
                assert enc[i] <= enc[j]
            if ri == rj:
                assert enc[i] == enc[j]


def test_integer_returns_lose_their_lattice() -> None:
    """Differences of warped integer returns are not multiples of one step (the gcd attack's premise)."""
    codec = _codec(_hardened(2, 5))
    enc = np.array([codec.scale(k) for k in range(8, 40)])
    steps = np.diff(enc)
    assert steps.max() / steps.min() > 1.2
    paper = Codec(_hardened(2, 5), encode_params=True, scale_rewards=True)
    assert np.allclose(np.diff([paper.scale(k) for k in range(8, 40)]), paper.scale(1.0))


def test_hidden_diagnostics_never_reach_an_entry_and_components_get_maps_of_their_own() -> None:
    s = _hardened(3, 1)
    codec = _codec(s)
    fb = Feedback(ret=40.0, components={"alive": 40.0, "ctrl": -2.0}, diagnostics={"episode_length": 40.0, "termination": "pole_fell"},
                  episode_returns=(40.0,))
    enc = encode_feedback(codec, fb)
    assert "episode_length" not in enc.diagnostics and enc.diagnostics["termination"] == "pole_fell"
    # the same raw value through the return's map and a component's: different maps, so anchors never add up
    assert enc.ret == codec.scale(40.0) and enc.components["alive"] == codec.scale(40.0, "alive") != enc.ret
    for name in ("alive", "ctrl"):  # each component's map is increasing, and fixed by the key
        xs = np.linspace(-300, 300, 61)
        ys = [codec.scale(x, name) for x in xs]
        assert np.all(np.diff(ys) > 0) and ys == [_codec(s).scale(x, name) for x in xs]
    entry = codec.entry(0, codec.encode(np.zeros(3)), enc.ret, enc.components, fb.diagnostics)
    assert dict(entry.diagnostics) == {"termination": "pole_fell"}


def test_integer_returns_are_dithered_below_one_step_so_no_integer_survives_the_warp() -> None:
    """Decoded with the true c, s, p, a hardened return is r + d with d in (-1/2, 1/2) keyed by the value:
    ties stay ties, distinct integers keep their order, and the decoded values are not integers."""
    s = _hardened(2, 3)
    codec = Codec(s, encode_params=True, scale_rewards=True, offsets=True, warp_params=True, warp_rewards=True, box=BOX,
                  resolution={"return": 1.0})
    r = np.arange(8, 500)
    enc = np.array([codec.scale(float(k)) for k in r])
    assert np.all(np.diff(enc) > 0) and codec.scale(37.0) == codec.scale(37.0)
    p, c, s0 = s.exponent, s.c, s.reward_origin
    w = lambda x, q: np.sign(x) * np.abs(x) ** q  # noqa: E731
    decoded = w(enc / c + w(s0, p), 1 / p)
    frac = decoded - r
    assert np.all(np.abs(frac) < 0.5) and np.std(frac) > 0.2  # spread over the whole step, not near 0
    # a mean over 4 episodes has step 1/4: its dither stays below that, so 10.25 < 10.5 still holds
    four = Codec(s, encode_params=True, scale_rewards=True, offsets=True, warp_params=True, warp_rewards=True, box=BOX,
                 resolution={"return": 1.0}, episodes=4)
    assert four.scale(10.25) < four.scale(10.5) < four.scale(10.75)
    # the paper's pure scale is untouched
    paper = Codec(s, encode_params=True, scale_rewards=True, resolution={"return": 1.0})
    assert paper.scale(37.0) == s.c * 37.0


def test_hardened_locomotion_hides_the_survive_component() -> None:
    from ppprops.client.hardening import residual_component

    ant = get_task("Ant-Ultra")
    assert residual_component(ant) == frozenset({"reward_survive"})
    cfg = make_config("Ant-Ultra", "pp-hardened")
    codec = codec_for(generate_secrets("h", ant, cfg.encoding), ant, cfg.encoding)
    fb = Feedback(ret=900.0, components={"reward_forward": 100.0, "reward_survive": 1000.0, "reward_ctrl": -199.0, "reward_contact": -1.0},
                  diagnostics={"episode_length": 1000.0, "termination": "time_limit"}, episode_returns=(900.0,))
    enc = encode_feedback(codec, fb)
    assert set(enc.components) == {"reward_forward", "reward_ctrl", "reward_contact"}
    text = build_prompt(prompt_context(ant, cfg.prompt, codec), [codec.entry(0, codec.encode(np.zeros(ant.D)), enc.ret, enc.components,
                                                                         enc.diagnostics)])
    assert "reward_survive" not in text and "episode_length" not in text
    pp = make_config("Ant-Ultra", "pp")
    assert "reward_survive" in encode_feedback(codec_for(generate_secrets("p", ant, pp.encoding), ant, pp.encoding), fb).components


def test_warmup_shows_the_same_numbers_whatever_the_secrets() -> None:
    """The hardened warm-up is drawn in the encoded space: what the provider sees carries no secret."""
    task = get_task("CartPole")
    cfg = make_config("CartPole", "pp-hardened", seed=4)
    shown = []
    for k in range(3):
        secrets = generate_secrets(f"h{k}", task, cfg.encoding)
        codec = codec_for(secrets, task, cfg.encoding)
        sampler = warmup_sampler(task.D, cfg.box, Streams(cfg.seed), cfg.mechanisms, codec)
        raws = [sampler.ask(i).theta for i in range(5)]
        assert all(np.all((t > -6) & (t < 6)) for t in raws)
        shown.append(np.round([codec.encode(t) for t in raws], 9))
    assert np.array_equal(shown[0], shown[1]) and np.array_equal(shown[1], shown[2])
    # the public box times the hardened prior's largest a_j (3), times the grid's public scale G (1 here)
    assert np.all(np.abs(shown[0]) <= 18 * codec.public_scale) and np.abs(shown[0]).max() > 12 * codec.public_scale
    # the paper's warm-up: the shown numbers are A theta, different for every key
    pp = make_config("CartPole", "pp", seed=4)
    sampler = warmup_sampler(task.D, pp.box, Streams(pp.seed), pp.mechanisms, codec)
    enc = [codec_for(generate_secrets(f"p{k}", task, pp.encoding), task, pp.encoding).encode(sampler.ask(0).theta) for k in range(2)]
    assert not np.allclose(enc[0], enc[1])


def test_hardened_prompt_wording_states_nothing_the_encoding_does_not_keep() -> None:
    task = get_task("CartPole")
    cfg = make_config("CartPole", "pp-hardened", number_format="grid")
    codec = codec_for(generate_secrets("h", task, cfg.encoding), task, cfg.encoding)
    ctx = prompt_context(task, cfg.prompt, codec)
    fb = Feedback(ret=23.0, components={}, diagnostics={"episode_length": 23.0, "termination": "pole_fell"}, episode_returns=(23.0,))
    enc = encode_feedback(codec, fb)
    e = codec.entry(0, codec.encode(np.full(task.D, 0.5)), enc.ret, enc.components, enc.diagnostics)
    text = build_prompt(ctx, [e])
    G = codec.public_scale  # the grid's public scale: the encoded warm-up box is the public box times 3 G
    assert ctx.warmup_range == (-18 * G, 18 * G) and round(18 * G) == 999
    assert "increasing transformation" in text and "drawn uniformly from [-999, 999] in these encoded coordinates" in text
    assert "Signs and order are kept" not in text and "multiplied by one positive constant" not in text
    assert "episode_length" not in text and "termination" not in text  # hide_anchors: termination=time_limit would pin 500
    old = replace(cfg, mechanisms=resolve("pp-hardened", hide_anchors=False))  # as pp-hardened was: the termination shown
    codec = codec_for(generate_secrets("h", task, old.encoding), task, old.encoding)
    enc = encode_feedback(codec, fb)
    e = codec.entry(0, codec.encode(np.full(task.D, 0.5)), enc.ret, enc.components, enc.diagnostics)
    assert "diagnostics: termination=pole_fell" in build_prompt(prompt_context(task, old.prompt, codec), [e])
    assert "500" not in set(re.findall(r"-?\d+(?:\.\d+)?", text)) and "optimal return" not in text


def test_each_switch_draws_only_the_secret_it_needs() -> None:
    task = get_task("CartPole")
    pp = make_config("CartPole", "pp")
    s = generate_secrets("x", task, replace(pp, mechanisms=resolve("pp", hide_return_diagnostics=True)).encoding)
    assert s.m is None and s.s is None and s.p is None
    s = generate_secrets("y", task, replace(pp, mechanisms=resolve("pp", secret_offsets=True)).encoding)
    assert s.m is not None and s.s is not None and s.p is None
    full = generate_secrets("z", task, make_config("CartPole", "pp-hardened").encoding)
    assert full.has_extras and full.m is not None and full.p is not None


def test_an_interrupted_hardened_run_resumes_to_the_same_history(tmp_path: Path) -> None:
    """Same key file, same warm-up draw, same encodings: resume continues exactly where it stopped."""
    from unittest import mock

    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.runner import resume, start
    from ppprops.store import open_store

    from support import offline_llm

    cfg = make_config("CartPole", "pp-hardened", warmup=4, iterations=4, final_episodes=0, seed=2)
    secrets = Secrets.generate_hardened("resume-h", get_task("CartPole").D, box=BOX, reward_scale=500.0)
    with offline_llm():
        start(cfg, tmp_path / "whole", secrets=secrets)

    class Dies(EchoOptimizer):
        def send(self, request, *, seed=None):  # type: ignore[no-untyped-def]
            if self.calls == 2:
                raise KeyboardInterrupt
            return super().send(request, seed=seed)

    with mock.patch("ppprops.llm.client.connect", lambda *args, **kwargs: Dies()), pytest.raises(KeyboardInterrupt):
        start(cfg, tmp_path / "cut", secrets=secrets)
    with offline_llm():
        resume(tmp_path / "cut")
    runs = []
    for name in ("whole", "cut"):
        store = open_store(tmp_path / name)
        runs.append([(c.params.tolist(), c.params_enc.tolist(), c.feedback_enc.ret) for c in store.candidates()])
        store.close()
    assert len(runs[0]) == 8 and runs[0] == runs[1]
