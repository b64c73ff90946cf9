"""What `ppprops --help`, `ppprops ask` and `ppprops tell` load: a robot driven from the shell
starts the last two twice per trial, so each builds only the parser it needs and imports neither
the settings schema nor the privacy, experiment, LLM or search modules. Nothing here is timed
(benchmarks/bench_startup.py measures the CPU time); these tests keep the structure that makes
them fast, and check that the command line built for one subcommand is the one built for all.
"""

from __future__ import annotations

import argparse
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
