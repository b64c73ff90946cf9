"""For every preset, the prompt holds what the paper says and nothing it must not."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from ppprops.client.codec import Codec, encode_feedback
from ppprops.client.context import prompt_context
from ppprops.client.secrets import Secrets
from ppprops.evaluation import Feedback
from ppprops.store import Candidate
from ppprops.tasks import get_task
from ppprops.wire import build_prompt, top_k
from ppprops.wire.numbers import fmt_sig, fmt_vector
from ppprops.wire.prompt import history_entry, template

from support import make_config

SECTIONS = ["1. The task description:", "2. The policy parameters:", "3. The feedback:", "4. How we will interact:", "5. Here is the history:"]


def _setup(method: str, task: str = "CartPole", **kw: object):  # type: ignore[no-untyped-def]
    t = get_task(task)
    kw.setdefault("number_format", "decimal")  # the decimal format's writing (the grid's: test_number_formats.py)
    cfg = make_config(task, method, **kw)
    rng = np.random.default_rng(3)
    secrets = Secrets(run_id="r", a=np.exp(rng.uniform(np.log(0.1), np.log(10), t.D)), c=3.7193)
    codec = Codec(secrets, encode_params=cfg.mechanisms.encode_params, scale_rewards=cfg.mechanisms.scale_rewards)
    ctx = prompt_context(t, cfg.prompt, codec)
    cands = []
    for i, r in enumerate([23.0, 131.0, 47.0]):
        theta = rng.uniform(-6, 6, t.D)
        fb = Feedback(ret=r, components={}, diagnostics={"episode_length": r, "termination": "pole_fell"}, episode_returns=(r,))
        cands.append(Candidate(i, i, "warmup", theta, codec.encode(theta), fb, encode_feedback(codec, fb), 0, (i,)))
    entries = [codec.entry(c.index, c.params_enc, c.feedback_enc.ret, c.feedback_enc.components, c.feedback_enc.diagnostics) for c in cands]
    return ctx, cands, entries, secrets


@pytest.mark.parametrize("method", ["vanilla", "pe", "df", "pp"])
def test_five_sections_in_order_with_best_last(method: str) -> None:
    ctx, cands, entries, _ = _setup(method)
    text = build_prompt(ctx, top_k(entries, 10))
    positions = [text.index(s) for s in SECTIONS]
    assert positions == sorted(positions)
    history = text[positions[-1] :]
    rets = [float(x) for x in re.findall(r"^return: (\S+)$", history, flags=re.M)]
    assert rets == sorted(rets) and len(rets) == 3


def _numbers(text: str) -> set[str]:
    return set(re.findall(r"-?\d+(?:\.\d+)?", text))


def test_vanilla_discloses_raw_values_reward_structure_and_optimum() -> None:
    ctx, cands, entries, _ = _setup("vanilla")
    text = build_prompt(ctx, entries)
    assert "The global optimal return is about 500.00" in text
    assert "+1 for every step" in text  # reward structure
    assert "Every parameter must lie in [-6, 6]" in text
    assert "encoded" not in text and "undisclosed" not in text and "not disclosed" not in text
    for c in cands:
        assert fmt_vector(list(c.params), 2, digits=3, sep=",") in text
        assert f"return: {c.ret:.2f}" in text
    assert "diagnostics:" not in text  # scalar feedback only


def test_pe_encodes_parameters_only() -> None:
    ctx, cands, entries, secrets = _setup("pe")
    text = build_prompt(ctx, entries)
    assert "encoded coordinate system" in text
    assert "The global optimal return is about 500.00" in text and "+1 for every step" in text
    for c in cands:
        assert f"return: {c.ret:.2f}" in text  # rewards stay raw in pe
        assert fmt_vector(list(c.params), 2, digits=3, sep=",") not in text
        assert fmt_vector(list(c.params_enc), 2, digits=3, sep=",") in text
    assert "[-6, 6]" not in text  # the range would reveal A
    assert "diagnostics:" not in text


def test_df_adds_detailed_feedback_on_raw_values() -> None:
    ctx, cands, entries, _ = _setup("df")
    text = build_prompt(ctx, entries)
    assert "diagnostics: episode_length=23, termination=pole_fell" in text
    assert "- diagnostic termination:" in text
    assert "The global optimal return is about 500.00" in text
    assert "Every parameter must lie in [-6, 6]" in text
    assert "encoded" not in text


def test_pp_encodes_scales_keeps_detail_and_withholds_the_optimum() -> None:
    ctx, cands, entries, secrets = _setup("pp")
    text = build_prompt(ctx, entries)
    assert "encoded coordinate system" in text and "multiplied by one positive constant" in text
    assert "diagnostics: episode_length=23, termination=pole_fell" in text
    assert "optimal return" not in text
    assert "500" not in _numbers(text)  # neither the optimum nor the step limit that states it
    assert "+1 for every step" not in text and "[-6, 6]" not in text
    for c in cands:
        assert f"return: {c.ret:.2f}" not in text
        assert f"return: {secrets.c * c.ret:.2f}" in text
        raw = ", ".join(f"{v:.2f}" for v in c.params)
        assert raw not in text


def test_each_mechanism_is_its_own_setting() -> None:
    _, _, entries, _ = _setup("vanilla")
    from dataclasses import replace

    from ppprops.methods import resolve

    t = get_task("CartPole")
    cfg = replace(make_config("CartPole", "vanilla"), mechanisms=resolve("vanilla", scale_rewards=True, disclose_optimum=False))
    secrets = Secrets(run_id="r", a=np.ones(t.D), c=2.0)
    codec = Codec(secrets, encode_params=False, scale_rewards=True)
    ctx = prompt_context(t, cfg.prompt, codec)
    text = build_prompt(ctx, entries)
    assert "multiplied by one positive constant" in text and "optimal return" not in text
    assert "Every parameter must lie in [-6, 6]" in text


def test_optimum_is_scaled_when_both_disclosed_and_scaled() -> None:
    from dataclasses import replace

    from ppprops.methods import resolve

    t = get_task("CartPole")
    cfg = replace(make_config("CartPole", "pp"), mechanisms=resolve("pp", disclose_optimum=True))
    codec = Codec(Secrets(run_id="r", a=np.ones(t.D), c=0.5), encode_params=True, scale_rewards=True)
    assert "The global optimal return is about 250.00" in build_prompt(prompt_context(t, cfg.prompt, codec), [])


def test_raw_candidates_are_refused_by_the_prompt_builder() -> None:
    ctx, cands, _, _ = _setup("pp")
    with pytest.raises(TypeError, match="EncodedEntry"):
        history_entry(ctx, cands[0])  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="EncodedEntry"):
        build_prompt(ctx, cands)  # type: ignore[arg-type]


def test_history_limit_wording_and_unbounded() -> None:
    ctx, _, entries, _ = _setup("pp", top_k=0)
    assert "every policy evaluated so far" in build_prompt(ctx, entries)


def test_templates_are_files() -> None:
    for name in [
        "prompt",
        "task",
        "parameters_raw",
        "parameters_encoded",
        "feedback_scalar",
        "feedback_detailed",
        "interaction",
        "history_entry",
        "correction",
    ]:
        assert template(name).template.strip()


def test_props_params_form_shows_the_same_values_pair_by_pair() -> None:
    ctx, _, entries, _ = _setup("pp")
    compact = build_prompt(ctx, entries)
    props = build_prompt(replace(ctx, params_style="indexed"), entries)
    e = entries[0]
    pairs = ", ".join(f"params[{i}]: {v:.2f}".replace("-0.00", "0.00") for i, v in enumerate(e.params))
    assert pairs in props and "params: [" not in props and "params: [" in compact
    assert len(props) > len(compact)
    with pytest.raises(ValueError, match="unknown params style 'csv'"):
        build_prompt(replace(ctx, params_style="csv"), entries)


def test_static_first_layout_changes_only_the_tail_between_iterations() -> None:
    """What a prefix cache keeps when the worst of K=2 entries drops out: with the default layout
    every fixed section; history first, only the opening line."""
    ctx, _, entries, _ = _setup("pp")

    def shared(a: str, b: str) -> int:
        return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))

    before, after = build_prompt(ctx, top_k(entries[:2], 2)), build_prompt(ctx, top_k(entries, 2))
    assert shared(before, after) > after.index("5. Here is the history:")
    hf = replace(ctx, layout="history-first")
    hb, ha = build_prompt(hf, top_k(entries[:2], 2)), build_prompt(hf, top_k(entries, 2))
    assert shared(hb, ha) < ha.index("1. Here is the history:") + 40 < ha.index("2. The task description:")
    for section in ("The task description:", "The policy parameters:", "The feedback:", "How we will interact:"):
        assert after.split(section)[1].split("\n\n")[0] == ha.split(section)[1].split("\n\n")[0]


@pytest.mark.parametrize(("x", "shown"), [(-33.77, "-33.8"), (0.59, "0.59"), (5.425, "5.42"), (123.4, "123"), (0.004, "0.00"),
                                         (-0.001, "0.00"), (9.996, "10.00"), (0.0, "0.00")])
def test_parameters_keep_three_significant_digits_at_most_two_decimals(x: float, shown: str) -> None:
    assert fmt_sig(x, 3, 2) == shown
    assert fmt_sig(x, 0, 2) == f"{x:.2f}".replace("-0.00", "0.00")  # 0 digits: fixed decimals, as --param-digits 0 asks
