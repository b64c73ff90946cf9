"""What `ppprops --help`, `ppprops ask` and `ppprops tell` load: a robot driven from the shell
starts the last two twice per trial, so each builds only the parser it needs and imports neither
the settings schema nor the privacy, experiment, LLM or search modules. Nothing here is timed
(benchmarks/bench_startup.py measures the CPU time); these tests keep the structure that makes
them fast, and check that the command line built for one subcommand is the one built for all.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from ppprops import cli


# -- the parser built for one subcommand is the parser built for all ------------------------------
def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _helps(parser: argparse.ArgumentParser, path: str = "ppprops") -> dict[str, str]:
    """The help text of ``parser`` and of every subcommand below it, by command line."""
    out = {path: parser.format_help()}
    for act in parser._actions:
        if isinstance(act, argparse._SubParsersAction):
            for name, sub in act.choices.items():
                out.update(_helps(sub, f"{path} {name}"))
    return out


def test_each_subcommand_alone_is_built_as_in_the_whole_parser() -> None:
    whole = _helps(cli.build_parser())
    names = list(_subparsers(cli.build_parser()))
    assert names == list(cli.commands())
    for name in names:
        alone = _helps(cli.parser_for([name]))
        assert alone["ppprops"] == whole["ppprops"]
        mine = {k: v for k, v in alone.items() if k == f"ppprops {name}" or k.startswith(f"ppprops {name} ")}
        assert mine == {k: v for k, v in whole.items() if k == f"ppprops {name}" or k.startswith(f"ppprops {name} ")}, name
    assert _helps(cli.run_parser(), "ppprops run") == {k: v for k, v in whole.items() if k.startswith("ppprops run")}


def test_the_command_table_says_what_the_modules_adding_them_say() -> None:
    """``cli.commands`` holds the one-line help of every subcommand (``ppprops --help`` needs no
    other module); the modules that add several subcommands at once say the same."""
    from ppprops.experiments.cli import add_subcommands
    from ppprops.privacy.commands import add_privacy_commands
    from ppprops.tasks.commands import add_task_commands

    class Recorder:
        def __init__(self) -> None:
            self.helps: dict[str, Any] = {}

        def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
            self.helps[name] = kwargs
            return argparse.ArgumentParser(prog=name)

    rec = Recorder()
    add_privacy_commands(rec, argparse.ArgumentParser)  # type: ignore[arg-type]
    add_task_commands(rec, argparse.ArgumentParser)  # type: ignore[arg-type]
    add_subcommands(rec)
    table = cli.commands()
    assert set(rec.helps) == {"audit", "privacy-report", "task", "experiment", "report"}
    for name, kwargs in rec.helps.items():
        assert kwargs == {"help": table[name].help}, name


def _parse(parser: argparse.ArgumentParser, argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[object, str, str]:
    try:
        result: object = vars(parser.parse_args(argv))
    except SystemExit as e:
        result = ("exit", e.code)
    out, err = capsys.readouterr()
    return result, out, err


@pytest.mark.parametrize("argv", [["ask", "d"], ["tell", "d", "0", "--return", "1", "--component", "a=1"], ["tell", "d", "x"],
                                  ["--version", "run"], ["-h", "tell"], ["--nope", "show", "d"], ["-1"], ["", "run"], ["--", "run"],
                                  ["ru"], ["run", "--env", "ask"], ["run", "--box", "-6,6", "--warm", "2"], ["policy", "eval", "f"],
                                  ["-6,6", "run"], ["study", "finalize", "d", "--return", "-3"], ["audit", "d", "--sim-steps", "9"],
                                  ["ask"], ["tell", "--help"], []])  # fmt: skip
def test_a_command_line_parses_as_with_the_whole_parser(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """``cli.parser_for(argv)`` gives what ``cli.build_parser()`` gives for ``argv``: the same
    namespace, or the same help, version or one-line error and exit code."""
    assert _parse(cli.parser_for(argv), argv, capsys) == _parse(cli.build_parser(), argv, capsys)


# -- what each command loads ------------------------------------------------------------------------
_LOADED = """
import json, os, sys
from ppprops.cli import main
try:
    main(sys.argv[2:])
except SystemExit:
    pass
with open(sys.argv[1], "w") as f:
    json.dump({"modules": sorted(sys.modules), "blas": os.environ.get("OPENBLAS_THREAD_TIMEOUT")}, f)
"""

# Never for ask (a stored trial) or tell: the attacks and the audit, the experiment grids, the settings
# table, the LLM clients and the embedded model, the prompt forms and proposers, the env loop, the worker pool, the
# optional extras; tell loads the run's schema (pydantic), its task and codec, nothing more.
NEVER = ("ppprops.privacy.simfit", "ppprops.privacy.attacks", "ppprops.privacy.audit", "ppprops.privacy.commands",
         "ppprops.experiments", "ppprops.settings", "ppprops.api", "ppprops.runner", "ppprops.llm.client", "ppprops.llm.embedded",
         "ppprops.llm.recording", "ppprops.proposers.llm", "ppprops.strategies", "ppprops.wire.forms", "ppprops.wire.parse",
         "ppprops.wire.document", "ppprops.policy_file", "ppprops.baselines.rl", "ppprops.tasks.commands", "ppprops.env_loop",
         "multiprocessing", "concurrent.futures", "urllib.request", "http.client", "openai", "httpx", "torch", "gymnasium", "scipy", "yaml", "ray",
         "xllamacpp")  # fmt: skip
# ask re-prints a stored trial from the store: not even the schema, the task, the codec or the study.
NEVER_ASK = (*NEVER, "pydantic", "ppprops.config", "ppprops.methods", "ppprops.tasks", "ppprops.study", "ppprops.client.codec",
             "ppprops.wire", "ppprops.evaluation")  # fmt: skip


def _run(tmp_path: Path, argv: list[str], env: dict[str, str] | None = None) -> dict[str, Any]:
    """What ``ppprops *argv`` leaves in a fresh process: its modules, and OPENBLAS_THREAD_TIMEOUT."""
    out = tmp_path / "loaded.json"
    proc = subprocess.run([sys.executable, "-c", _LOADED, str(out), *argv], capture_output=True, text=True, timeout=300,
                          env=env)  # fmt: skip
    assert out.exists(), proc.stderr
    doc: dict[str, Any] = json.loads(out.read_text())
    return doc


def _loaded(tmp_path: Path, argv: list[str]) -> set[str]:
    return set(_run(tmp_path, argv)["modules"])


def _found(loaded: set[str], never: tuple[str, ...]) -> list[str]:
    return sorted(m for m in loaded if any(m == n or m.startswith(n + ".") for n in never))


@pytest.fixture(scope="module")
def asked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A study whose first trial is asked for and stored (pending)."""
    study = tmp_path_factory.mktemp("startup") / "study"
    assert cli.main(["study", "create", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "2",
                     "--out", str(study)]) == 0  # fmt: skip
    assert cli.main(["ask", str(study)]) == 0
    return study


def test_help_loads_the_command_line_alone(tmp_path: Path) -> None:
    loaded = _loaded(tmp_path, ["--help"])
    assert {m for m in loaded if m.startswith("ppprops")} == {"ppprops", "ppprops.cli", "ppprops.errors", "ppprops.version"}
    assert "numpy" not in loaded and "pydantic" not in loaded and "dataclasses" not in loaded


def test_asking_for_a_stored_trial_loads_the_store_alone(tmp_path: Path, asked: Path) -> None:
    loaded = _loaded(tmp_path, ["ask", str(asked)])
    assert "ppprops.store" in loaded and "ppprops.study_commands" in loaded  # it did ask
    assert _found(loaded, NEVER_ASK) == []


def test_tell_loads_no_search_attack_or_llm_module(tmp_path: Path, asked: Path) -> None:
    study = tmp_path / "study"
    shutil.copytree(asked, study)
    loaded = _loaded(tmp_path, ["tell", str(study), "0", "--return", "1"])
    assert "ppprops.study" in loaded and "ppprops.client.codec" in loaded  # it did tell
    assert _found(loaded, NEVER) == []


def test_the_check_sees_a_module_loaded(tmp_path: Path, asked: Path) -> None:
    """The check above is live: the full path of ask (no stored trial) loads what NEVER_ASK names."""
    study = tmp_path / "study"
    shutil.copytree(asked, study)
    assert cli.main(["tell", str(study), "0", "--return", "1"]) == 0
    assert {"pydantic", "ppprops.study", "ppprops.tasks"} <= set(_found(_loaded(tmp_path, ["ask", str(study)]), NEVER_ASK))


def test_ask_and_tell_leave_the_environment_as_they_found_it(tmp_path: Path, asked: Path) -> None:
    """numpy loads with OpenBLAS's idle threads sleeping at once (``OPENBLAS_THREAD_TIMEOUT``, read
    when it loads); the variable is gone afterwards (nothing started later inherits it), and one
    the user set is left alone."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    for argv in (["ask", str(asked)], ["tell", str(tmp_path / "study"), "0", "--return", "1"]):
        shutil.rmtree(tmp_path / "study", ignore_errors=True)
        shutil.copytree(asked, tmp_path / "study")
        assert _run(tmp_path, argv, env)["blas"] is None
        shutil.rmtree(tmp_path / "study")
        shutil.copytree(asked, tmp_path / "study")
        assert _run(tmp_path, argv, {**env, "OPENBLAS_THREAD_TIMEOUT": "12"})["blas"] == "12"
