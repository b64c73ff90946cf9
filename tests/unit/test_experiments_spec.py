"""Experiment specs expand into the runs the paper's tables need, configured as `ppprops run` would;
grid secrets derive deterministically from the master key with Secrets' own distributions."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import stat
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import build_parser, run_config
from ppprops.client.secrets import LOG_HIGH, LOG_LOW, Secrets
from ppprops.config import RunConfig
from ppprops.errors import ConfigError
from ppprops.experiments import paper_values as pv
from ppprops.experiments.grid import MASTER_KEY, Grid, create_master_key, derive_secrets, read_master_key
from ppprops.experiments.spec import build_spec, flags_table, load_spec, read_spec_file
from ppprops.methods import get_method

ROOT = Path(__file__).resolve().parents[2]
SPECS = ROOT / "experiments"
# The paper's LaTeX source is not part of the repository: $PPPROPS_PAPER_TEX names it, else a
# workspace that keeps it beside the clone (../shared/paper); without it the check is skipped.
PAPER = Path(os.environ.get("PPPROPS_PAPER_TEX") or ROOT.parent / "shared" / "paper" / "pp-props-paper.tex")
TEN = ["Ant-Ultra", "Ant-Joints", "Ant-Torso", "Humanoid-Ultra", "Humanoid-Joints", "Humanoid-Torso",
       "Acrobot", "CartPole", "FetchReachDense", "Highway"]  # fmt: skip


def _cli_config(*argv: str) -> RunConfig:
    return run_config(build_parser().parse_args(["run", *argv]))


def test_main_results_spec_is_the_papers_grid() -> None:
    spec = load_spec(SPECS / "main_results.toml")
    assert len(spec.runs) == 10 * 4 * 5
    assert {r.task for r in spec.runs} == set(TEN)
    assert {r.method for r in spec.runs} == {"vanilla", "pe", "df", "pp"}
    assert {r.seed for r in spec.runs} == set(range(5))
    for r in spec.runs:
        c = r.config
        assert (c["warmup"], c["iterations"], c["top_k"], c["episodes"], c["final_episodes"]) == (10, 50, 10, 1, 20)
    assert spec.runs[0].seed == 0 and spec.runs[-1].seed == 4  # seed-major: early seeds complete first
    assert len({r.name for r in spec.runs}) == len(spec.runs)


def test_bounded_history_spec_compares_k10_with_unbounded() -> None:
    spec = load_spec(SPECS / "bounded_history.toml")
    assert len(spec.runs) == 3 * 2 * 5
    by_label = {label: {r.config["top_k"] for r in spec.runs if r.label == label} for label in ("K10", "unbounded")}
    assert by_label == {"K10": {10}, "unbounded": {0}}
    assert {r.method for r in spec.runs} == {"vanilla"}
    assert {r.task for r in spec.runs} == {"Ant-Ultra", "Ant-Joints", "Ant-Torso"}


def test_baselines_spec_skips_what_the_paper_marks_not_applicable() -> None:
    spec = load_spec(SPECS / "baselines.toml")
    search = [r for r in spec.runs if r.kind == "search"]
    rl = [r for r in spec.runs if r.kind == "rl"]
    assert len(search) == 6 * 3 * 5
    r2po = [r for r in search if r.method == "r2po"]
    assert r2po and all(r.config["episodes"] == 20 for r in r2po)  # the CLI's r2po default, not re-implemented
    # continuous tasks (Ant, Humanoid, Fetch): ppo a2c sac td3 ddpg trpo; discrete ones: ppo a2c trpo dqn
    assert len(rl) == (3 * 6 + 3 * 4) * 5
    assert "CartPole rl-sac" in spec.skipped and "Ant-Ultra rl-dqn" in spec.skipped
    assert not any(r.task == "CartPole" and r.method == "rl-sac" for r in rl)


def test_smoke_yaml_spec_parses() -> None:
    spec = load_spec(SPECS / "smoke.yaml")
    assert len(spec.runs) == 2 * 2 * 2 and spec.runs[0].config["iterations"] == 2


def test_a_grid_run_is_configured_exactly_as_ppprops_run() -> None:
    spec = build_spec(flags_table(["CartPole", "Acrobot"], ["vanilla", "pp", "cmaes"], 2),
                      overrides={"warmup": 3, "top_k": 0, "encode_params": True})  # fmt: skip
    # r2po with encoded parameters is refused in a grid exactly as by ppprops run
    with pytest.raises(ConfigError, match="--method r2po shows the critic raw states"):
        build_spec(flags_table(["CartPole"], ["r2po"], 1), overrides={"encode_params": True})
    for r in spec.runs:
        prompted = get_method(r.method).uses_llm
        # ppprops run refuses prompt settings for a method that sends no prompt (--top-k with cmaes); a grid's shared
        # table keeps them for every run, where they do nothing
        top_k = ["--top-k", "0"] if prompted else []
        expected = _cli_config("--env", r.task, "--method", r.method, "--seed", str(r.seed), "--warmup", "3", *top_k,
                               "--encode-params", "on")  # fmt: skip
        assert RunConfig.from_json(r.config) == (expected if prompted else dataclasses.replace(expected, top_k=0))
    with pytest.raises(ConfigError, match="--top-k does not apply to --method cmaes: it sends no prompt"):
        _cli_config("--env", "CartPole", "--method", "cmaes", "--top-k", "0")


def test_spec_settings_and_flags_layer_like_run_config(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('seeds = [3, 7]\n[run]\nwarmup = 4\ntop-k = 5\nbox = [-2, 2]\n'
                    '[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\nrun = { top-k = 2, iterations = 1 }\n')  # fmt: skip
    spec = load_spec(path, overrides={"warmup": 6})
    assert [r.seed for r in spec.runs] == [3, 7]
    c = spec.runs[0].config
    assert (c["warmup"], c["top_k"], c["iterations"], c["box"]) == (6, 2, 1, [-2.0, 2.0])
    assert load_spec(path, seeds=1).runs[0].seed == 0


def test_yaml_and_toml_specs_agree(tmp_path: Path) -> None:
    (tmp_path / "a.toml").write_text('seeds = 2\n[run]\nwarmup = 2\n[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp", "random"]\n')
    (tmp_path / "a.yaml").write_text("seeds: 2\nrun: {warmup: 2}\ngrid:\n  - {tasks: [CartPole], methods: [pp, random]}\n")
    a, b = load_spec(tmp_path / "a.toml"), load_spec(tmp_path / "a.yaml")
    assert [(r.name, r.config) for r in a.runs] == [(r.name, r.config) for r in b.runs]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\n[run]\ntop_kk = 3\n', "unknown run setting 'top_kk'"),
        ('[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\n[run]\nseed = 3\n', "set by the grid"),
        ('[[grid]]\ntasks = ["CartPole"]\nmethods = ["ppo"]\n', "unknown method 'ppo'"),
        ('[[grid]]\ntasks = ["CartPol"]\nmethods = ["pp"]\n', "unknown task"),
        ('[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\n[run]\nwarmup = "x"\n', "must be an integer"),
        ('[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\nlabel = "a b"\n', "label"),
        ('name = "x"\n', "no runs"),
        ('[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\n[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\n', "give one of them a label"),
        ('[[rl]]\ntasks = ["CartPole"]\nalgos = ["ppo"]\n', "timesteps is required"),
        ('colour = 1\n[[grid]]\ntasks = ["CartPole"]\nmethods = ["pp"]\n', "unknown key"),
    ],
)
def test_bad_specs_are_one_clear_error(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_spec(path)


def test_invalid_toml_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[[grid]\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        read_spec_file(path)


def test_master_key_is_private_and_derivation_is_deterministic(tmp_path: Path) -> None:
    key = create_master_key(tmp_path / MASTER_KEY)
    assert stat.S_IMODE(os.stat(tmp_path / MASTER_KEY).st_mode) == 0o600
    assert read_master_key(tmp_path / MASTER_KEY) == key
    cfg = RunConfig.from_json(build_spec(flags_table(["Acrobot"], ["pp"], 1)).runs[0].config)
    s1, s2 = derive_secrets(key, "Acrobot__pp__0", cfg), derive_secrets(key, "Acrobot__pp__0", cfg)
    other = derive_secrets(key, "Acrobot__pp__1", cfg)
    assert s1.fingerprint() == s2.fingerprint() != other.fingerprint()
    assert derive_secrets(os.urandom(32), "Acrobot__pp__0", cfg).fingerprint() != s1.fingerprint()
    assert s1.run_id == "Acrobot__pp__0" and len(s1.a) == 21 and s1.m is None


def test_derived_secrets_follow_the_documented_distribution() -> None:
    """ln a_j and ln c uniform on [ln 0.1, ln 10]: checked on many draws (mean, spread, range)."""
    cfg = RunConfig.from_json(build_spec(flags_table(["CartPole"], ["pp"], 1)).runs[0].config)
    key = bytes(range(32))
    logs = np.concatenate([np.log(derive_secrets(key, f"run{i}", cfg).a) for i in range(300)])
    cs = np.log([derive_secrets(key, f"run{i}", cfg).c for i in range(300)])
    for x in (logs, cs):
        assert x.min() >= LOG_LOW - 1e-12 and x.max() <= LOG_HIGH + 1e-12
        assert abs(x.mean()) < 0.2  # the midpoint of [ln 0.1, ln 10] is 0
        assert abs(x.std() - (LOG_HIGH - LOG_LOW) / math.sqrt(12)) < 0.12


def test_hardened_runs_get_every_hardened_secret() -> None:
    spec = build_spec(flags_table(["CartPole"], ["pp-hardened"], 1))
    cfg = RunConfig.from_json(spec.runs[0].config)
    s = derive_secrets(bytes(32), spec.runs[0].name, cfg)
    assert s.m is not None and s.s is not None and s.p is not None
    lo, hi = cfg.box
    assert np.all((s.m >= lo + (hi - lo) / 4 - 1e-9) & (s.m <= hi - (hi - lo) / 4 + 1e-9))
    assert 1.25 - 1e-9 <= max(s.p, 1 / s.p) <= 2.0 + 1e-9
    # the same fields are set as on secrets drawn the ordinary way (the grid refuses to run otherwise)
    from ppprops.client.hardening import generate_secrets

    ref = generate_secrets("x", cfg.make_task(), cfg.encoding)
    assert [f for f in Secrets.__dataclass_fields__ if getattr(ref, f) is None] == \
           [f for f in Secrets.__dataclass_fields__ if getattr(s, f) is None]  # fmt: skip


def test_rerunning_a_grid_with_other_settings_is_refused(tmp_path: Path) -> None:
    spec = build_spec(flags_table(["CartPole"], ["random"], 1), overrides={"iterations": 3})
    Grid.open(tmp_path / "g", spec)
    Grid.open(tmp_path / "g", spec)  # the same spec again: fine
    more = build_spec(flags_table(["CartPole"], ["random"], 2), overrides={"iterations": 3})
    Grid.open(tmp_path / "g", more)  # more seeds: fine, the grid grows
    changed = build_spec(flags_table(["CartPole"], ["random"], 1), overrides={"iterations": 4})
    with pytest.raises(ConfigError, match="other settings.*iterations"):
        Grid.open(tmp_path / "g", changed)
    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "x.txt").write_text("x")
    with pytest.raises(ConfigError, match="not a grid directory"):
        Grid.open(tmp_path / "h", spec)


def _spoil(doc: dict, how: str) -> str:  # type: ignore[type-arg]
    run = next(iter(doc["runs"]))
    if how == "run entry is a number":
        doc["runs"][run] = 5
    elif how == "run config is a string":
        doc["runs"][run]["config"] = "x"
    elif how == "run seed is missing":
        del doc["runs"][run]["seed"]
    elif how == "runs is a list":
        doc["runs"] = []
    elif how == "other format":
        doc["format"] = "ppprops.grid/0"
    elif how == "no invocations":
        del doc["invocations"]
    return json.dumps(doc)


@pytest.mark.parametrize("how,problem", [
    ("not json", "not a JSON object"), ("a list", "not a JSON object"), ("other format", "format is not"),
    ("runs is a list", "runs missing or of the wrong type"), ("no invocations", "invocations or runs missing"),
    ("run entry is a number", "run entry 'CartPole__random__0'"), ("run config is a string", "run entry 'CartPole__random__0'"),
    ("run seed is missing", "run entry 'CartPole__random__0'"),
])  # fmt: skip
def test_a_corrupt_grid_manifest_is_refused_and_left_as_it_is(tmp_path: Path, how: str, problem: str) -> None:
    """A grid.json that is not JSON, not an object, of another format, or with a malformed run table
    or run entry is one ConfigError naming the file and the problem (never an AssertionError, a
    TypeError or an AttributeError), and the file is not rewritten."""
    spec = build_spec(flags_table(["CartPole"], ["random"], 1), overrides={"iterations": 3})
    Grid.open(tmp_path / "g", spec)
    manifest = tmp_path / "g" / "grid.json"
    text = {"not json": "not json", "a list": "[]"}.get(how) or _spoil(json.loads(manifest.read_text()), how)
    manifest.write_text(text)
    with pytest.raises(ConfigError, match=r"grid\.json is corrupt \(.*" + re.escape(problem)):
        Grid.open(tmp_path / "g", spec)
    assert manifest.read_text() == text


def test_paper_values_match_the_papers_main_table() -> None:
    if not PAPER.is_file():
        pytest.skip(f"the paper's LaTeX source is not in this clone ({PAPER} is absent; set PPPROPS_PAPER_TEX to check "
                    "paper_values.py against it)")
    text = PAPER.read_text(encoding="utf-8")
    body = text[text.index(r"\label{tab:all_results}"):text.index(r"\end{tabular}", text.index(r"\label{tab:all_results}"))]
    names = {"Highway Env": "Highway"}
    rows = re.findall(r"\n([A-Za-z][A-Za-z -]+?)\s*\n((?:& .*\n){5})", body)
    assert len(rows) == 10
    for name, cells in rows:
        task = names.get(name.strip(), name.strip())
        for method, cell in zip(("vanilla", "r2po", "pe", "df", "pp"), cells.strip().splitlines()):
            nums = re.findall(r"-?\d+(?:\.\d+)?", re.sub(r"\\textbf|\$\^\\dagger\$|\\\\", "", cell))
            ref = pv.main_value(task, method)
            assert ref is not None
            if not nums:
                assert ref.mean is None and "overflow" in ref.note
            else:
                assert (ref.mean, ref.std) == (float(nums[0]), float(nums[1])), (task, method)


def test_experiment_dry_run_lists_runs_and_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from ppprops.cli import main

    out = tmp_path / "grid"
    assert main(["experiment", str(SPECS / "bounded_history.toml"), "--out", str(out), "--dry-run", "--seeds", "1",
                 "--tasks", "Ant-Ultra"]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "2 runs" in text and "pending  Ant-Ultra__vanilla-K10__0" in text and "Ant-Ultra__vanilla-unbounded__0" in text
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--tasks", "CartPole"], "give a spec file, or --tasks and --methods"),
        (["--tasks", "CartPole", "--methods", "ppx"], "unknown method 'ppx'"),
        (["--tasks", "CartPole", "--methods", "pp", "--top-k", "-1"], "--top-k must be >= 0"),
        (["--tasks", "CartPole", "--methods", "pp", "--seeds", "0"], "seeds must be in [1, 10000]"),
        (["--tasks", "CartPole", "--methods", "pp", "--llm-threads", "0"], "--llm-threads must be in"),
    ],
)
def test_experiment_input_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    from ppprops.cli import main

    assert main(["experiment", "--out", str(tmp_path / "g"), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "g").exists()
