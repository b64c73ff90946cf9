"""Command-line manners: flags as the README writes them, a quiet exit when the reader of stdout
goes away, the run directory named at the start, progress on stderr, `--json` for `run` and
`resume`, and help text for every option."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from ppprops.cli import build_parser, main, run_config, run_parser
from ppprops.experiments.spec import run_settings
from ppprops.store import open_store

TINY = ["--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "1", "--final-episodes", "3", "--select-top", "0"]


def _ppprops(args: list[str], **kw) -> subprocess.CompletedProcess[str]:  # type: ignore[no-untyped-def]
    return subprocess.run([sys.executable, "-m", "ppprops", *args], capture_output=True, text=True, timeout=300, **kw)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("manners") / "run"
    assert main(["run", *TINY, "--out", str(out), "--quiet"]) == 0
    return out


# -- --box as the README writes it ------------------------------------------------------------
@pytest.mark.parametrize("text,box", [("-6,6", (-6.0, 6.0)), ("-3.5,2", (-3.5, 2.0)), ("-.5,.5", (-0.5, 0.5)), ("0,6", (0.0, 6.0))])
def test_box_with_a_leading_minus_is_a_value(text: str, box: tuple[float, float]) -> None:
    assert run_config(run_parser().parse_args(["--env", "CartPole", "--box", text])).box == box
    assert run_config(run_parser().parse_args(["--env", "CartPole", f"--box={text}"])).box == box
    ex = build_parser().parse_args(["experiment", "--tasks", "CartPole", "--methods", "pp", "--out", "g", "--box", text])
    assert ex.box == box


@pytest.mark.parametrize("value", ['"-6,6"', "[-6, 6]", '"-6, 6"'])
def test_box_in_a_config_file_and_a_spec(tmp_path: Path, value: str, capsys) -> None:  # type: ignore[no-untyped-def]
    cfg = tmp_path / "run.toml"
    cfg.write_text(f'env = "CartPole"\nmethod = "random"\nwarmup = 2\niterations = 0\nfinal-episodes = 0\nbox = {value}\n')
    out = tmp_path / "run"
    assert main(["run", "--config", str(cfg), "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    store = open_store(out)
    assert store.config()["box"] == [-6.0, 6.0]
    store.close()
    spec_value = tomllib.loads(f"box = {value}")["box"]  # an experiment spec's [run] table reads it alike
    assert run_settings({"box": spec_value}, "spec")["box"] == (-6.0, 6.0)


def test_the_readme_command_line_runs(tmp_path: Path) -> None:
    proc = _ppprops(["run", *TINY, "--box", "-6,6", "--out", str(tmp_path / "r"), "--quiet"])
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""


# -- a closed stdout (`| head -1`) is a quiet exit ------------------------------------------------
def _closed_stdout(args: list[str]) -> subprocess.CompletedProcess[bytes]:
    """Run with stdout a pipe whose reading end is already closed: the first write fails with EPIPE."""
    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run([sys.executable, "-m", "ppprops", *args], stdout=w, stderr=subprocess.PIPE, timeout=300)
    finally:
        os.close(w)


@pytest.mark.parametrize("args", [["show", "{run}"], ["show", "{run}", "--json"], ["envs"], ["envs", "--json"],
                                  ["audit", "{run}"], ["policy", "eval", "{run}/best_policy.json", "--episodes", "2", "--quiet"],
                                  ["report", "{run}", "--out", "{tmp}/report"], ["--help"], ["run", "--help"]])  # fmt: skip
def test_closed_stdout_exits_quietly(finished_run: Path, tmp_path: Path, args: list[str]) -> None:
    proc = _closed_stdout([a.format(run=finished_run, tmp=tmp_path) for a in args])
    assert proc.stderr == b"", proc.stderr.decode()
    assert proc.returncode in (0, 141)  # --help exits through argparse, which prints before failing quietly


def test_show_piped_to_head(finished_run: Path) -> None:
    proc = subprocess.run(f"{sys.executable} -m ppprops show {finished_run} | head -1", shell=True, capture_output=True, text=True)
    assert proc.stderr == "" and proc.stdout.startswith("run      ") and proc.stdout.count("\n") == 1


def test_a_run_whose_reader_went_away_finishes_quietly(tmp_path: Path) -> None:
    out = tmp_path / "r"
    proc = _closed_stdout(["run", *TINY, "--out", str(out), "--quiet"])
    assert proc.returncode == 141 and proc.stderr == b""
    store = open_store(out)
    assert store.status() == "finished"
    store.close()


# -- the run directory at the start, progress on stderr, --json -------------------------------------
def test_default_run_directory_is_printed_at_the_start(tmp_path: Path) -> None:
    proc = _ppprops(["run", *TINY], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    first = proc.stderr.splitlines()[0]
    # no --seed: a seed is drawn, printed and stored; the directory is named by the run's id (no ':' in it)
    m = re.fullmatch(r"run directory: (runs/CartPole__random__(\d+)__\d{8}-\d{6}-[0-9a-f]{4}) \(seed (\d+)\)", first)
    assert m is not None and m.group(2) == m.group(3), first
    run_dir = m.group(1)
    assert json.loads(_ppprops(["show", run_dir, "--json"], cwd=tmp_path).stdout)["run_id"] == Path(run_dir).name
    assert (tmp_path / run_dir / "best_policy.json").exists()
    assert f"run directory: {run_dir}" in proc.stdout.splitlines()  # and again with the summary
    assert "final evaluation" in proc.stderr and "3/3" in proc.stderr  # the final evaluation's progress


def test_run_and_resume_print_one_json_object(tmp_path: Path) -> None:
    out = tmp_path / "r"
    proc = _ppprops(["run", *TINY, "--out", str(out), "--json"])
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)  # the whole of stdout is one object
    assert doc["run_dir"] == str(out) and doc["status"] == "finished" and len(doc["candidates"]) == 3
    assert doc["privacy_audit"].startswith("privacy audit:")
    assert "final evaluation" in proc.stderr  # progress stays on stderr
    proc = _ppprops(["resume", str(out), "--json"])
    assert proc.returncode == 0, proc.stderr
    again = json.loads(proc.stdout)
    assert again["run_dir"] == str(out) and again["final_eval"] == doc["final_eval"]


def test_policy_eval_shows_progress(finished_run: Path) -> None:
    proc = _ppprops(["policy", "eval", str(finished_run / "best_policy.json"), "--episodes", "4"])
    assert proc.returncode == 0 and "CartPole policy eval" in proc.stderr and "4/4" in proc.stderr
    assert proc.stdout.startswith("CartPole: mean return")
    quiet = _ppprops(["policy", "eval", str(finished_run / "best_policy.json"), "--episodes", "4", "--quiet", "--json"])
    assert quiet.stderr == "" and json.loads(quiet.stdout)["episodes"] == 4


def test_ctrl_c_elsewhere_is_one_line_and_130(monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    import ppprops.cli as cli

    def interrupted(a: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_cmd_envs", interrupted)
    assert main(["envs"]) == 130
    assert capsys.readouterr().err == "ppprops: interrupted\n"


def test_ctrl_c_before_the_run_directory_exists(monkeypatch, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    import ppprops.runner as runner

    def interrupted(*args: object, **kw: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(runner.Study, "create", interrupted)
    out = tmp_path / "r"
    assert main(["run", *TINY, "--out", str(out), "--quiet"]) == 130
    assert capsys.readouterr().err == f"ppprops: interrupted before the run directory {out} was created; nothing was saved\n"


# -- help text ------------------------------------------------------------------------------------
def _actions(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.Action]]:
    found = []
    for act in parser._actions:
        if isinstance(act, argparse._SubParsersAction):
            for name, sub in act.choices.items():
                found += _actions(sub, f"{path} {name}")
        elif not isinstance(act, (argparse._HelpAction, argparse._VersionAction)):
            found.append((path, act))
    return found


def test_every_option_has_help_text() -> None:
    actions = _actions(build_parser(), "ppprops")
    missing = [f"{path} {act.option_strings or act.dest}" for path, act in actions if not act.help or act.help == argparse.SUPPRESS]
    assert not missing
    paths = {path for path, _ in actions}
    assert {"ppprops show", "ppprops resume", "ppprops policy eval", "ppprops run"} <= paths
