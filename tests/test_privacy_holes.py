"""Every outgoing byte is read by the audit, R2PO refuses privacy it cannot keep, grids take
each hardening switch alone, the request seed and the fallback state no secret, and the new attacks
(warped lattice, locomotion components, fallbacks) are measured against pp and pp-hardened."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_attacks import seeded_secrets
from test_audit import _last_request, build_run, shown_vector

from ppprops import seeding
from ppprops.cli import main
from ppprops.client.codec import grid_factor, grid_scale
from ppprops.client.hardening import generate_secrets
from ppprops.config import RunConfig
from ppprops.experiments.grid import derive_secrets
from ppprops.experiments.spec import build_spec, flags_table
from ppprops.methods import HARDENING, check_method, resolve
from ppprops.privacy.attacks import run_attacks
from ppprops.privacy.audit import audit_run
from ppprops.privacy.matrix import privacy_report
from ppprops.privacy.requests import load_requests
from ppprops.privacy.simulate import EchoOptimizer
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.wire.numbers import fmt

from support import make_config, offline_llm, tamper_call


# -- R2PO ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("flags", [["--encode-params", "on"], ["--scale-rewards", "on"], ["--hide-return-diagnostics", "on"]])
def test_r2po_refuses_every_privacy_mechanism_with_one_line(tmp_path: Path, flags: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--env", "CartPole", "--method", "r2po", *flags, "--out", str(tmp_path / "r"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--method r2po shows the critic raw states and actions" in err[0]
    assert flags[0] + " on" in err[0] and not (tmp_path / "r").exists()


def test_r2po_without_privacy_mechanisms_and_pp_with_them_are_allowed() -> None:
    check_method("r2po", resolve("vanilla"))
    check_method("r2po", resolve("vanilla", detailed_feedback=True, disclose_optimum=False))
    check_method("pp", resolve("pp-hardened"))


# -- grids with each hardening switch alone ---------------------------------------------------------
ALONE = [h for h in HARDENING if h != "encoded_warmup"]  # an encoded warm-up needs warped parameters (refused alone)


@pytest.mark.parametrize("switch", ALONE)
def test_grid_secrets_come_from_the_one_routine_for_each_switch_alone(switch: str) -> None:
    spec = build_spec(flags_table(["CartPole"], ["pp"], 1), overrides={switch: True})
    cfg = RunConfig.from_json(spec.runs[0].config)
    assert getattr(cfg.mechanisms, switch) and sum(getattr(cfg.mechanisms, h) for h in HARDENING) == 1
    key = bytes(range(32))
    s = derive_secrets(key, spec.runs[0].name, cfg)
    assert s.fingerprint() == derive_secrets(key, spec.runs[0].name, cfg).fingerprint()
    ref = generate_secrets("x", cfg.make_task(), cfg.encoding)
    assert [f for f in ("m", "s", "p") if getattr(s, f) is None] == [f for f in ("m", "s", "p") if getattr(ref, f) is None]
    assert (s.m is not None) == (switch == "secret_offsets") and (s.p is not None) == (switch == "warp_rewards")
    # the same routine with the same generator gives the same secrets: runs and grids cannot drift apart
    from ppprops.experiments.grid import derived_rng

    again = generate_secrets(spec.runs[0].name, cfg.make_task(), cfg.encoding, rng=derived_rng(key, spec.runs[0].name))
    assert again.fingerprint() == s.fingerprint()


@pytest.mark.parametrize("flag", ["--secret-offsets", "--warp-params"])
def test_a_grid_with_one_hardening_switch_runs(tmp_path: Path, flag: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "grid"
    code = main(["experiment", "--tasks", "CartPole", "--methods", "pp", "--seeds", "2", "--warmup", "3", "--iterations", "0",
                 "--final-episodes", "1", "--jobs", "1", flag, "on", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    for seed in range(2):
        key = json.loads((out / "runs" / f"CartPole__pp__{seed}" / "secrets.key").read_text())
        assert ("m" in key) == (flag == "--secret-offsets") and "p" not in key


# -- the audit reads every byte ---------------------------------------------------------------------
def _shown(run: Path) -> Any:
    store = open_store(run)
    cands = store.candidates()
    store.close()
    _, text = _last_request(run)
    return next(c for c in cands if shown_vector(c.params_enc) in text and c.ret > 20)


def _prose(doc: dict[str, Any], sentence: str) -> None:
    doc["messages"][0]["content"] = doc["messages"][0]["content"].replace("\n\n4. How we will interact:",
                                                                          f" {sentence}\n\n4. How we will interact:", 1)


def _diagnostic(doc: dict[str, Any], c: Any, text: str) -> None:
    """A diagnostics line added to the entry of ``c`` (pp-hardened shows none of its own)."""
    content = doc["messages"][0]["content"]
    start = content.index(shown_vector(c.params_enc) + "\nreturn: " + fmt(c.feedback_enc.ret, 2))
    end = content.index("\n\n", start)
    doc["messages"][0]["content"] = content[:end] + f"\ndiagnostics: {text}" + content[end:]


PLACEMENTS: dict[str, Callable[[dict[str, Any], Any], None]] = {
    "top-level user field": lambda d, c: d.update(user=f"client {int(c.ret)}"),
    "top-level metadata field": lambda d, c: d.update(metadata={"note": f"best so far {c.ret:.1f}"}),
    "assistant message": lambda d, c: d["messages"].insert(1, {"role": "assistant", "content": f"The return was {int(c.ret)}."}),
    "system message": lambda d, c: d["messages"].insert(0, {"role": "system", "content": f"Raw return: {int(c.ret)}"}),
    "content as a list of parts": lambda d, c: d["messages"][0].update(
        content=[{"type": "text", "text": d["messages"][0]["content"]}, {"type": "text", "text": f"(raw {c.ret:g})"}]),
    "schema description": lambda d, c: d.update(response_format={"type": "json_schema", "json_schema": {
        "name": "policy_parameters", "schema": {"type": "object", "description": f"target above {c.ret:.2f}"}}}),
    "seed field": lambda d, c: d.update(seed=int(c.ret)),
    "return as an integer in the prose": lambda d, c: _prose(d, f"The best return so far is {int(c.ret)}."),
    "return with one decimal in the prose": lambda d, c: _prose(d, f"The best return so far is {c.ret:.1f}."),
    "return with two decimals in the prose": lambda d, c: _prose(d, f"The best return so far is {c.ret:.2f}."),
    "raw parameters in the prose": lambda d, c: _prose(d, "Start from " + "[" + ", ".join(fmt(v, 2) for v in c.params) + "]."),
    "episode_length in an entry": lambda d, c: _diagnostic(d, c, f"episode_length={int(c.ret)}"),
    "raw parameter inside an entry": lambda d, c: d["messages"][0].update(content=d["messages"][0]["content"].replace(
        shown_vector(c.params_enc), shown_vector(list(c.params_enc[:4]) + [c.params[4]] + list(c.params_enc[5:])), 1)),
}


@pytest.fixture(scope="module")
def hardened_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = build_run(tmp_path_factory.mktemp("placements"), "pp-hardened")
    assert audit_run(run).exit_code(strict=True) == 0  # the baseline is clean, even under --strict
    return run


@pytest.mark.parametrize("where", list(PLACEMENTS))
def test_a_raw_value_planted_anywhere_in_a_request_fails_the_audit(hardened_run: Path, tmp_path: Path, where: str) -> None:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(hardened_run, run)
    c = _shown(run)
    tamper_call(run, request=lambda d: PLACEMENTS[where](d, c))
    r = audit_run(run)
    assert r.exit_code() == 1 and r.leaks, r.format()
    kinds = {f.kind for f in r.leaks}
    assert kinds & {"raw_return", "raw_param"}, r.format()
    assert any("call 6" in loc or "transcript" in loc for f in r.leaks for loc in f.locations)


def test_a_request_with_an_unexpected_field_is_unverified_even_without_numbers(hardened_run: Path, tmp_path: Path) -> None:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(hardened_run, run)
    tamper_call(run, request=lambda d: d.update(user="someone"))
    r = audit_run(run)
    assert r.exit_code() == 1 and not r.leaks and [f.detail for f in r.unverified] == ["field user, which the client never sends"]


# -- the request seed and the fallback ---------------------------------------------------------------
def test_the_request_seed_is_keyed_not_derived_from_the_run_seed(tmp_path: Path) -> None:
    seeds = []
    for k in range(2):
        run = tmp_path / f"r{k}"
        with offline_llm():
            start(make_config("CartPole", "pp", warmup=3, iterations=2, final_episodes=0, seed=0), run)
        store = open_store(run)
        seeds.append([json.loads(c["request"])["seed"] for c in store.llm_calls()])
        store.close()
        assert all(s != seeding.llm_seed(0, it, 0) for it, s in enumerate(seeds[-1]))
    assert seeds[0] != seeds[1]  # same run seed, other secrets: other sampling seeds


class _Unusable(EchoOptimizer):
    """Answers every other call with something unparseable, so the run has many fallbacks."""

    def send(self, request, *, seed=None):  # type: ignore[no-untyped-def]
        ex = super().send(request, seed=seed)
        return replace(ex, content="no idea") if self.calls % 2 == 0 or len(request.messages) > 1 else ex


def test_fallbacks_are_drawn_in_the_encoded_space_so_their_spread_states_no_secret(tmp_path: Path) -> None:

    run = tmp_path / "fb"
    secrets = seeded_secrets("pp", "CartPole", 3)
    config = make_config("CartPole", "pp", warmup=6, iterations=16, final_episodes=0, seed=0, parse_retries=0, number_format="grid")
    start(config, run, secrets=secrets, llm=_Unusable(config.llm))
    store = open_store(run)
    cands = store.candidates()
    store.close()
    fallbacks = [c for c in cands if c.source == "fallback"]
    assert len(fallbacks) >= 6
    est = next(e for e in run_attacks(load_requests(run), "CartPole", (-6.0, 6.0)) if e.attack == "fallback-spread")
    assert est.applicable, est.detail
    a = np.asarray(est.value, dtype=float)
    known = np.isfinite(a)
    # the noise is keyed by the secrets (no replay from the run seed) and drawn at a public width in the
    # encoded space: its spread measures that width, a_j about G (the grid's public scale), whatever the true a_j is
    G = grid_scale((-6.0, 6.0), warp_params=False)
    true = grid_factor(secrets, (-6.0, 6.0), warp_params=False) * secrets.a  # the effective scale g a_j
    assert known.sum() >= 5 and "spread of" in est.detail, (a, est.detail)
    assert np.median(np.abs(np.log(a[known] / G))) < 0.35, a  # about the public width
    assert np.median(np.abs(np.log(true[known] / G))) > 0.5  # the true scales are far from G
    assert np.median(np.abs(np.log(a[known] / true[known]))) > 0.5  # so the estimate is not them


# -- the new attacks on pp and pp-hardened --------------------------------------------------------------
def _simulate(root: Path, task: str, method: str, seed: int, iterations: int = 20, warmup: int = 10, **switches: bool) -> Path:
    out = root / f"{task}__{method}__{seed}"
    config = make_config(task, method, warmup=warmup, iterations=iterations, final_episodes=0, seed=seed)
    if switches:
        config = replace(config, mechanisms=resolve(method, **switches))
    with offline_llm():
        start(config, out, secrets=seeded_secrets(method, task, seed))
    return out


def _estimate(run: Path, task: str, attack: str) -> Any:
    return next(e for e in run_attacks(load_requests(run), task, (-6.0, 6.0)) if e.attack == attack)


@pytest.mark.parametrize("task", ["CartPole", "Acrobot"])
def test_warped_lattice_recovers_c_under_pp_and_the_old_undithered_warp_but_not_under_pp_hardened(
        tmp_path: Path, task: str, monkeypatch: pytest.MonkeyPatch) -> None:
    pp = _simulate(tmp_path, task, "pp", 1)
    est = _estimate(pp, task, "warped-lattice")
    assert est.applicable and abs(est.value / seeded_secrets("pp", task, 1).c - 1) < 0.01, est.detail
    hard = [_estimate(_simulate(tmp_path, task, "pp-hardened", s), task, "warped-lattice") for s in range(3)]
    assert not any(e.applicable for e in hard), [e.detail for e in hard]
    # the red team's finding: without the dither the warp keeps integer structure, and the lattice search finds c, s, p
    import ppprops.client.hardening as hardening

    facts = hardening.facts_for
    monkeypatch.setattr(hardening, "facts_for", lambda name: facts(name).model_copy(update={"resolution": {}}))
    # (it needs a favourable draw: 1 of these 8 seeded runs on CartPole, 2 on Acrobot)
    # ... and the diagnostics that mark a cap shown, as pp-hardened showed them then (the lattice's anchor)
    old = [(s, _estimate(_simulate(tmp_path / "old", task, "pp-hardened", s, hide_anchors=False), task, "warped-lattice"))
           for s in range(8)]
    hits = [(s, e) for s, e in old if e.applicable]
    assert hits, [e.detail for _, e in old]
    for s, e in hits:
        assert abs(e.value / seeded_secrets("pp-hardened", task, s).c - 1) < 0.01


def test_privacy_report_has_every_attack_row(tmp_path: Path) -> None:
    runs = [_simulate(tmp_path, "CartPole", m, 0, iterations=6) for m in ("pp", "pp-hardened")]
    text, _ = privacy_report(runs)
    for row in ("warped-lattice", "additivity", "survive-length", "saturated-ctrl", "fallback-spread"):
        assert f"| {row} |" in text
    assert "audit exposed" in text


def test_ant_components_give_c_under_pp_and_nothing_under_pp_hardened(tmp_path: Path) -> None:
    pytest.importorskip("mujoco")
    runs: dict[tuple[str, int], dict[str, Any]] = {}

    def attacks(method: str, seed: int) -> dict[str, Any]:
        if (method, seed) not in runs:
            run = _simulate(tmp_path, "Ant-Ultra", method, seed, iterations=2, warmup=6)
            runs[method, seed] = {e.attack: e for e in run_attacks(load_requests(run), "Ant-Ultra", (-6.0, 6.0))}
        return runs[method, seed]

    def c(method: str, seed: int) -> float:
        return seeded_secrets(method, "Ant-Ultra", seed).c

    # the survive component gives c under pp; under pp-hardened neither it nor the components' sum is shown
    pp = attacks("pp", 0)
    assert pp["survive-length"].applicable and abs(pp["survive-length"].value / c("pp", 0) - 1) < 0.01, pp["survive-length"].detail
    hard = attacks("pp-hardened", 0)
    assert not hard["survive-length"].applicable and not hard["additivity"].applicable
    # saturated-ctrl fires only when two policies saturate the actions, which depends on the draw: the first of
    # seeds 0-7 where it fires must give c under pp, and must miss it under pp-hardened (the control cost has a
    # warped map of its own there). A preset on which it never fires fails the test: the claim went unchecked.
    for method, close in (("pp", True), ("pp-hardened", False)):
        seed = next((s for s in range(8) if attacks(method, s)["saturated-ctrl"].applicable), None)
        assert seed is not None, f"saturated-ctrl never applied under {method} in seeds 0-7"
        error = abs(attacks(method, seed)["saturated-ctrl"].value / c(method, seed) - 1)
        assert (error < 0.01) if close else (error > 0.05), (method, seed, error)


# -- token counting sends nothing ------------------------------------------------------------------
def test_counting_tokens_starts_no_client_and_sends_nothing() -> None:
    from ppprops.llm.client import connect
    from ppprops.proposers.r2po import estimate_tokens

    client = connect(make_config("CartPole", "vanilla").llm)
    assert estimate_tokens("x" * 1000) >= 500 and client._sdk is None
    client.close()


def test_r2po_estimates_prompt_tokens_from_the_usage_of_its_answers() -> None:
    from test_r2po import _proposer

    from ppprops.llm.client import Exchange

    p, _ = _proposer()
    assert p.prompt_tokens("y" * 1000) == 1000  # before any answer: the runner's estimate (here len)
    p._observe(Exchange("{}", None, "{}", None, 2000, 500, 10, 0.1, True))  # 1 token per 4 characters
    assert p.prompt_tokens("y" * 1000) == 263 + 32


def test_the_audit_rebuilds_the_r2po_critic_prompt_and_reads_what_differs(tmp_path: Path) -> None:
    cfg = replace(make_config("CartPole", "vanilla", warmup=3, iterations=2, episodes=2, final_episodes=0), method="r2po")
    with offline_llm():
        start(cfg, tmp_path / "r")
    r = audit_run(tmp_path / "r")
    assert not r.unverified and any(f.kind == "raw_trajectory" and f.by_design for f in r.leaks), r.format()
    assert all(f.by_design for f in r.leaks)  # everything R2PO shows raw is by design of that baseline
    store = open_store(tmp_path / "r")
    c = max(store.candidates(), key=lambda c: c.ret)
    store.close()

    def plant(d: dict[str, Any]) -> None:
        text = d["messages"][0]["content"]
        assert text.startswith("You are a critic")
        d["messages"][0]["content"] = text.replace("Per-episode diagnostics", f"Best so far: {c.ret:.1f}. Per-episode diagnostics", 1)

    tamper_call(tmp_path / "r", request=plant)
    r = audit_run(tmp_path / "r")
    assert any(f.kind == "raw_return" and not f.by_design for f in r.leaks), r.format()
    assert "by design" not in r.verdict()
