"""The transcript audit: clean on pp runs, and it finds every kind of leak planted in a transcript.

Runs here are built from the real codec, prompt builder and store (no LLM, no simulator), so the
planted values are exact; `test_pp_runs_through_the_runner_audit_clean` runs the whole loop with an
offline stand-in for the LLM, and test_privacy_wire.py audits runs with the embedded model.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from ppprops import rundir
from ppprops.cli import main
from ppprops.client import hardening
from ppprops.client.codec import encode_feedback
from ppprops.client.context import prompt_context
from ppprops.client.hardening import codec_for, generate_secrets
from ppprops.client.secrets import Secrets
from ppprops.errors import StoreError
from ppprops.evaluation import Feedback
from ppprops.llm.client import EndpointClient
from ppprops.llm.embedded import MODEL_ALIAS
from ppprops.llm.protocol import Exchange
from ppprops.privacy import simfit
from ppprops.privacy.audit import audit_run, renders, token_value
from ppprops.runner import create_run, start
from ppprops.store import Candidate, open_store
from ppprops.summary import format_summary, run_summary
from ppprops.tasks import get_task
from ppprops.wire import build_prompt, top_k
from ppprops.wire.numbers import fmt, fmt_sig, fmt_vector

from support import chat_request, find_call, make_config, offline_llm, tamper_call


def shown_vector(values: object) -> str:
    """A parameter vector as the default prompt form prints it."""
    return fmt_vector(list(values), 2, digits=3, sep=",")  # type: ignore[call-overload]


def build_run(root: Path, method: str, *, name: str | None = None, a_one: bool = False, repeat: tuple[int, int] | None = None,
              **settings: object) -> Path:
    """12 candidates (6 warm-up, then one request and one answer each), CartPole-like feedback with components.

    ``repeat=(i, j)``: candidate j is candidate i's policy again, with the same return but an episode
    that ended another way (as when the LLM proposes a policy a second time)."""
    task = get_task("CartPole")
    settings.setdefault("number_format", "decimal")  # the notations planted below are the decimal format's (the grid's: the test at the end)
    cfg = make_config("CartPole", method, warmup=6, iterations=6, final_episodes=0, seed=3, **settings)
    run_dir = root / (name or method)
    if cfg.encoding.mechanisms.hardened:  # fixed secrets: a fresh draw could land a meaningless fit within 1% by chance
        secrets = generate_secrets(f"audit-{method}", task, cfg.encoding, rng=np.random.default_rng(11))
    else:
        rng = np.random.default_rng(11)
        a = rng.uniform(1.7, 4.3, task.D)
        if a_one:
            a[0] = 1.0  # a factor of 1: that coordinate is sent as it is, which is not a leak anyone can see
        secrets = Secrets(run_id=f"audit-{method}", a=a, c=3.7193)
    store, secrets = create_run(cfg, run_dir, secrets)
    codec = codec_for(secrets, task, cfg.encoding)
    ctx = prompt_context(task, cfg.prompt, codec)
    client = EndpointClient(cfg.llm, base_url="http://127.0.0.1:9/v1", model=MODEL_ALIAS, api_key="x", grammar_ok=True)  # the real body
    rng = np.random.default_rng(5)
    entries = []
    thetas: list[np.ndarray] = []
    rets: list[float] = []
    for i in range(12):
        theta = rng.uniform(-6, 6, task.D)
        r = float(rng.integers(8, 200))
        end = "pole_fell"
        if repeat is not None and i == repeat[1]:
            theta, r, end = thetas[repeat[0]], rets[repeat[0]], "out_of_bounds"
        thetas.append(theta)
        rets.append(r)
        fb = Feedback(ret=r, components={"alive": r, "ctrl": round(-0.37 * (i + 1), 4)},
                      diagnostics={"episode_length": r, "termination": end}, episode_returns=(r,))
        enc = encode_feedback(codec, fb)
        c = Candidate(i, i if i < 6 else i - 6, "warmup" if i < 6 else "llm", theta, codec.encode(theta), fb, enc, 0, (i,))
        if i >= 6:  # the request that produced candidate i shows the history so far
            it = i - 6
            prompt = build_prompt(ctx, top_k(entries, cfg.top_k))
            body = client.body(chat_request([{"role": "user", "content": prompt}], task.D, iteration=it), seed=codec.sampling_seed(cfg.seed, it, 0))
            answer = json.dumps({"params": [round(float(v), 2) for v in codec.encode(theta)]})
            store.add_llm_call(it, 0, Exchange(json.dumps(body), None, answer, None, len(prompt), None, None, 0.0, True), None, form="chat")
        store.add_candidate(c)
        detailed = cfg.mechanisms.detailed_feedback
        entries.append(codec.entry(i, c.params_enc, enc.ret, enc.components if detailed else {}, enc.diagnostics if detailed else {}))
    store.close()
    return run_dir


@pytest.fixture(autouse=True)
def small_simulations(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulator attacks (tests/test_simulator_attacks.py) run within a small bound here: these tests are about the rest."""
    monkeypatch.setattr(simfit, "DEFAULT_LIMITS", simfit.SimLimits(vector_steps=500_000, env_steps=2_000))


def _last_request(run_dir: Path) -> tuple[int, str]:
    call = find_call(run_dir)
    return int(call["id"]), call["body"]["messages"][0]["content"]


def plant(run_dir: Path, old: str, new: str) -> None:
    """Rewrite the last recorded request, as if the client had sent ``new`` where it sent ``old``."""
    _, text = _last_request(run_dir)
    assert text.count(old) >= 1, old
    tamper_call(run_dir, request=lambda body: body["messages"][0].update(content=text.replace(old, new, 1)))


def _shown_candidate(run_dir: Path) -> Candidate:
    """A candidate whose entry is in the last request (with raw values distinct from the encoded ones)."""
    store = open_store(run_dir)
    cands = store.candidates()
    store.close()
    _, text = _last_request(run_dir)
    return next(c for c in cands[:11] if shown_vector(c.params_enc) in text)


@pytest.fixture()
def pp_run(tmp_path: Path) -> Path:
    return build_run(tmp_path, "pp")


def test_token_precision_covers_every_notation() -> None:
    assert token_value("47.60") == (47.6, pytest.approx(0.005))
    assert token_value("47.6")[1] == pytest.approx(0.05)  # type: ignore[index]
    assert token_value("48")[1] == 0.5  # type: ignore[index]
    assert token_value("4.764e+01")[1] == pytest.approx(0.005)  # type: ignore[index]
    assert token_value("-0.00") == (0.0, 0.005) and token_value("pole_fell") is None
    assert renders(47.6449, *token_value("47.64")) and not renders(47.646, *token_value("47.64"))  # type: ignore[misc]


def test_a_pp_transcript_sends_no_raw_value_but_fails_on_the_papers_channels(pp_run: Path) -> None:
    r = audit_run(pp_run)
    assert r.requests == 6 and r.entries > 30 and r.checked["params"] == 10 * r.entries and r.checked["components"] > 0
    assert r.leaks == [] and r.unverified == []
    # episode_length = the raw CartPole return and integer returns under a pure scale: attacks recover c within 1%
    assert {"diagnostic", "lattice"} <= {f.kind for f in r.exposed} and all(f.by_design for f in r.exposed)
    assert r.exit_code() == 1 and r.verdict().startswith("EXPOSED") and "channels PP-ProPS keeps as the paper defines it" in r.verdict()
    kinds = {f.kind for f in r.channels}
    assert {"diagnostic_return", "diagnostic_determines", "warmup_scale", "reward_lattice"} <= kinds
    assert "run_seed" not in kinds  # the warm-up of a new run is keyed by its secrets, not drawn from the run seed
    assert any("episode_length equals the raw return" in f.detail for f in r.channels)
    assert any("episode_length equals the raw component alive" in f.detail for f in r.channels)
    assert "not checked: request sizes" in r.format()


def test_a_factor_of_one_is_a_coincidence_not_a_leak(tmp_path: Path) -> None:
    r = audit_run(build_run(tmp_path, "pp", a_one=True))
    assert not r.leaks and not r.unverified and r.coincidences >= r.entries  # params[0] equals its raw value in every entry


def test_planted_raw_parameter_is_found_at_its_place(pp_run: Path) -> None:
    c = _shown_candidate(pp_run)
    shown = [fmt_sig(v, 3, 2) for v in c.params_enc]
    leaked = list(shown)
    leaked[3] = fmt(c.params[3], 2)
    plant(pp_run, "[" + ",".join(shown) + "]", "[" + ",".join(leaked) + "]")
    r = audit_run(pp_run)
    assert r.exit_code() == 1 and [f.kind for f in r.leaks] == ["raw_param"]
    assert "params[3]" in r.leaks[0].detail and f"candidate {c.index}" in r.leaks[0].locations[0]
    assert not r.leaks[0].by_design


@pytest.mark.parametrize("notation", ["{:.3e}", "{:.4f}", "{:.1f}"])
def test_planted_raw_parameter_in_other_notations(pp_run: Path, notation: str) -> None:
    c = _shown_candidate(pp_run)
    shown = [fmt_sig(v, 3, 2) for v in c.params_enc]
    leaked = list(shown)
    leaked[5] = notation.format(c.params[5])
    plant(pp_run, "[" + ",".join(shown) + "]", "[" + ",".join(leaked) + "]")
    assert [f.kind for f in audit_run(pp_run).leaks] == ["raw_param"]


def test_planted_raw_vector_is_found(pp_run: Path) -> None:
    c = _shown_candidate(pp_run)
    plant(pp_run, shown_vector(c.params_enc), shown_vector(c.params))
    r = audit_run(pp_run)
    assert r.exit_code() == 1 and r.leaks[0].kind == "raw_param" and f"candidate {c.index}" in r.leaks[0].locations[0]


@pytest.mark.parametrize("render", [lambda v: str(int(v)), lambda v: f"{v:.1f}", lambda v: f"{v:.3e}"])
def test_planted_raw_return_is_found_as_integer_short_decimals_or_exponent(pp_run: Path, render) -> None:  # type: ignore[no-untyped-def]
    c = _shown_candidate(pp_run)
    old = shown_vector(c.params_enc) + "\nreturn: " + fmt(c.feedback_enc.ret, 2)
    plant(pp_run, old, shown_vector(c.params_enc) + "\nreturn: " + render(c.ret))
    r = audit_run(pp_run)
    assert [f.kind for f in r.leaks] == ["raw_return"] and f"candidate {c.index}" in r.leaks[0].locations[0]


def test_planted_raw_component_is_found(pp_run: Path) -> None:
    c = _shown_candidate(pp_run)
    old = f"ctrl={fmt(c.feedback_enc.components['ctrl'], 2)}"
    plant(pp_run, old, f"ctrl={c.feedback.components['ctrl']:g}")
    r = audit_run(pp_run)
    assert [f.kind for f in r.leaks] == ["raw_component"] and "ctrl" in r.leaks[0].detail


@pytest.mark.parametrize("sentence", ["A good policy reaches 500.", "Aim for 500.00 or more.", "Target: 5.0e+02."])
def test_planted_optimum_in_the_prose_is_found(pp_run: Path, sentence: str) -> None:
    plant(pp_run, "\n\n4. How we will interact:", f" {sentence}\n\n4. How we will interact:")
    r = audit_run(pp_run)
    assert {f.kind for f in r.leaks} == {"optimum"} and not r.leaks[0].by_design


def test_planted_raw_return_in_the_prose_is_found(pp_run: Path) -> None:
    store = open_store(pp_run)
    c = store.candidates()[2]
    store.close()
    plant(pp_run, "\n\n4. How we will interact:", f" The best return so far is {c.ret:.2f}.\n\n4. How we will interact:")
    assert "raw_return" in {f.kind for f in audit_run(pp_run).leaks}


def test_an_entry_the_audit_cannot_account_for_fails_it(pp_run: Path) -> None:
    c = _shown_candidate(pp_run)
    plant(pp_run, shown_vector(c.params_enc), shown_vector([123.45] * len(c.params)))
    r = audit_run(pp_run)
    assert r.leaks == [] and r.unverified and r.exit_code() == 1 and r.verdict().startswith("UNVERIFIED")


@pytest.mark.parametrize("layout", ["static-first", "history-first"])
def test_the_audit_reads_the_props_params_form_and_either_layout(tmp_path: Path, layout: str) -> None:
    run = build_run(tmp_path, "pp", prompt_params="indexed", prompt_layout=layout)
    r = audit_run(run)
    assert not r.leaks and not r.unverified and r.entries >= 6 * 5 and r.checked["params"] == r.entries * get_task("CartPole").D, r.format()
    c = next(c for c in open_store(run).candidates()[:11] if f"params[0]: {fmt(c.params_enc[0], 2)}, params[1]:" in _last_request(run)[1])
    plant(run, f"params[2]: {fmt(c.params_enc[2], 2)},", f"params[2]: {fmt(c.params[2], 2)},")
    r = audit_run(run)
    assert [f.kind for f in r.leaks] == ["raw_param"] and "params[2]" in r.leaks[0].detail
    assert audit_run(build_run(tmp_path, "vanilla", name="v", prompt_params="indexed")).exit_code() == 1


def test_props_pairs_out_of_order_make_the_audit_unverified(tmp_path: Path) -> None:
    run = build_run(tmp_path, "pp", prompt_params="indexed")
    _, text = _last_request(run)
    first = text.index("params[0]: ")
    plant(run, text[first:text.index("params[2]: ", first)], text[first:text.index("params[1]: ", first)].replace("[0]", "[1]") + "params[0]: 1.00, ")
    r = audit_run(run)
    assert r.exit_code() == 1 and [f.detail for f in r.unverified] == ["history entry with unreadable parameters"], r.format()


@pytest.mark.parametrize("method", ["vanilla", "df"])
def test_vanilla_and_df_send_raw_values_by_design(tmp_path: Path, method: str) -> None:
    r = audit_run(build_run(tmp_path, method))
    kinds = {f.kind for f in r.leaks}
    assert r.exit_code() == 1 and "by design of preset" in r.verdict()
    assert {"raw_param", "raw_return", "optimum"} <= kinds and all(f.by_design for f in r.leaks)
    assert ("raw_component" in kinds) == (method == "df")


def test_hardened_transcript_is_clean_even_under_strict(tmp_path: Path) -> None:
    run = build_run(tmp_path, "pp-hardened")
    r = audit_run(run)
    assert r.exit_code(strict=True) == 0 and r.channels == [] and r.checked["params"] > 0 and r.checked["components"] > 0
    _, text = _last_request(run)
    assert "termination" not in text and "episode_length" not in text  # a time-limit termination would pin the return (hide_anchors)


def test_pp_runs_through_the_runner_audit_clean(tmp_path: Path) -> None:
    for task in ("CartPole", "Acrobot"):
        rng = np.random.default_rng(7)
        secrets = Secrets(run_id=f"runner-{task}", a=np.exp(rng.uniform(-2.3, 2.3, get_task(task).D)), c=0.731)
        with offline_llm():
            start(make_config(task, "pp", warmup=8, iterations=6, final_episodes=0), tmp_path / task, secrets=secrets)
        r = audit_run(tmp_path / task)
        assert r.requests == 6 and not r.leaks and not r.unverified, r.format()
        assert "diagnostic" in {f.kind for f in r.exposed}  # c = printed return / episode length (formula on Acrobot)
        if task == "Acrobot":  # return = -episode_length + success gives c; the -500 cap (success=0) too
            assert {"diagnostic", "known-cap"} <= {f.kind for f in r.exposed}


def test_cli_audit_exit_codes_and_the_self_audit_after_a_run(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    pp = build_run(tmp_path, "pp")
    assert main(["audit", str(pp)]) == 1  # EXPOSED: the paper's channels give c within 1%
    assert main(["audit", str(build_run(tmp_path, "pp-hardened"))]) == 0
    assert main(["audit", str(build_run(tmp_path, "pp-hardened", name="h2")), "--strict"]) == 0
    assert main(["audit", str(build_run(tmp_path, "vanilla")), "--json"]) == 1
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["exit_code"] == 1 and doc["findings"][0]["severity"] == "leak"
    assert main(["audit", str(tmp_path / "missing")]) == 2
    # fixed secrets and run id (which keys the streams: warm-up, episodes, sampling seeds, dither): drawn fresh,
    # the simulator fits of the full audit (sim-marginal-lattice on the four shown CartPole returns) read the best
    # shown raw return exactly, or c within 1%, on 16 of 300 draws (EXPOSED, as it should be: 6 of the 8 whose
    # best shown return was the cap of 500); on this draw they miss by far (c by 92%, the best return by 5 steps)
    monkeypatch.setattr(hardening, "os_rng", lambda: np.random.default_rng(3))
    monkeypatch.setattr(rundir, "new_run_id", lambda config: f"{config.task}__{config.method}__{config.seed}__20261204-000000-0000")
    with offline_llm():
        # a run seed beyond the provider's search (a small one is read off the transcript: test_simulator_attacks)
        assert main(["run", "--env", "CartPole", "--method", "pp-hardened", "--warmup", "3", "--iterations", "2",
                     "--final-episodes", "0", "--seed", "987654", "--out", str(tmp_path / "h"), "--quiet", "--audit", "full"]) == 0
    out = capsys.readouterr().out
    assert "privacy audit: CLEAN" in out and "Known channels" not in out
    key = json.loads((tmp_path / "h" / "secrets.key").read_text())
    # the secrets as a line would print them (4 decimals: 2 would match a return such as 11.00 when c rounds to 1.00)
    assert f"{key['c']:.4f}" not in out and f"{key['s']:.4f}" not in out


def test_a_directory_without_a_search_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(StoreError):
        audit_run(tmp_path)


@pytest.mark.parametrize("method", ["pp", "df"])
def test_a_policy_evaluated_twice_is_matched_by_every_printed_field(tmp_path: Path, method: str) -> None:
    """The LLM may propose a policy again: two candidates share the parameters and the return but not
    the episode's diagnostics. Each printed entry is the candidate whose fields it prints, so the
    audit accounts for both (it used to take the first for both and flag the second's diagnostics)."""
    run = build_run(tmp_path, method, repeat=(2, 9))
    _, text = _last_request(run)
    with open_store(run) as store:
        cands = store.candidates()
    assert text.count(shown_vector(cands[2].params_enc)) == 2  # both entries are in the last prompt
    assert "termination=out_of_bounds" in text and "termination=pole_fell" in text
    report = audit_run(run)
    assert not report.unverified and not [f for f in report.leaks if not f.by_design], report.format()
    plant(run, "termination=out_of_bounds", "termination=pole_flew")  # a field neither candidate has is still caught
    assert audit_run(run).unverified


@pytest.mark.parametrize("form", ["document", "chat"])
@pytest.mark.parametrize("fmt", ["grid", "decimal"])
def test_runs_in_each_number_format_audit_without_leaks_and_hardened_clean(tmp_path: Path, fmt: str, form: str) -> None:
    """A run in each number format (the grid's integers and the decimal format it replaced) and
    prompt form, through the runner with the offline stand-in: the audit reads every entry back in
    the run's own format (stored with its config), so nothing is unverified and nothing raw sent;
    pp-hardened is CLEAN."""
    for method in ("pp", "pp-hardened"):
        task = get_task("Acrobot")
        cfg = make_config("Acrobot", method, warmup=6, iterations=5, final_episodes=0, number_format=fmt, prompt_form=form)
        secrets = generate_secrets(f"fmt-{method}", task, cfg.encoding, rng=np.random.default_rng(21))
        run = tmp_path / f"{method}-{fmt}-{form}"
        with offline_llm():
            start(cfg, run, secrets=secrets)
        r = audit_run(run)
        assert r.requests >= 5 and not r.leaks and not r.unverified, r.format()
        assert r.checked["params"] >= 5 * 6  # every shown entry's parameters were matched in the run's format
        body = find_call(run)["body"]
        text = body["prompt"] if form == "document" else body["messages"][0]["content"]
        printed = re.findall(r"params: \[([^\]]*)\]", text)[0].split(",")
        values = [p.split(":")[-1] for p in printed]
        assert all(re.fullmatch(r"-?\d+", v) for v in values) == (fmt == "grid"), values
        summary = run_summary(run)  # show names the grid on its task line (decimal, the paper's format, goes unnamed)
        assert summary["number_format"] == fmt
        assert ("numbers grid" in format_summary(summary).splitlines()[1]) == (fmt == "grid")
        if method == "pp-hardened":
            assert r.exit_code() == 0 and r.verdict().startswith("CLEAN"), r.format()
