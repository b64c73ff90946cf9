"""One registry of methods: the CLI, the experiment specs, the runner and the reports ask it;
run status and kind are enums that read old stores unchanged."""

from __future__ import annotations

import ast
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ppprops import methods as registry
from ppprops import strategies
from ppprops.cli import build_parser, main, run_config, run_parser
from ppprops.config import RunConfig
from ppprops.errors import ConfigError
from ppprops.experiments import order as grid_order
from ppprops.experiments.spec import build_spec, flags_table
from ppprops.loop import Phase
from ppprops.methods import METHODS, Method, MethodKind, get_method, resolve
from ppprops.proposers.base import Proposal
from ppprops.runner import start
from ppprops.status import RunKind, RunStatus, is_complete
from ppprops.store import open_store

from support import make_config

ROOT = Path(__file__).resolve().parents[2]


def _choices(parser, dest: str) -> list[str]:  # type: ignore[no-untyped-def]
    return list(next(a for a in parser._actions if a.dest == dest).choices)


def test_the_cli_lists_exactly_the_registered_methods() -> None:
    assert _choices(run_parser(), "method") == [m.name for m in METHODS.values() if m.kind is not MethodKind.RL]
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices
    rl = next(a for a in sub["baseline"]._actions if a.dest == "baseline_command").choices["rl"]
    assert _choices(rl, "algo") == [m.algo for m in METHODS.values() if m.kind is MethodKind.RL]
    assert set(_choices(rl, "algo")) == {"ppo", "a2c", "sac", "td3", "ddpg", "trpo", "dqn"}
    assert grid_order.METHOD_ORDER == tuple(METHODS)  # the report's columns follow the registry
    assert grid_order.PROMPT_METHODS == ("vanilla", "pe", "df", "pp", "pp-hardened")


@pytest.mark.parametrize("method,kind,episodes", [("vanilla", MethodKind.PROMPTED, 1), ("r2po", MethodKind.PROMPTED, 20),
                                                  ("pp-hardened", MethodKind.PROMPTED, 1), ("random", MethodKind.BLACK_BOX, 1),
                                                  ("cmaes", MethodKind.BLACK_BOX, 1)])  # fmt: skip
def test_each_method_knows_its_kind_and_defaults(method: str, kind: MethodKind, episodes: int) -> None:
    cfg = run_config(run_parser().parse_args(["--env", "CartPole", "--method", method]))
    assert get_method(method).kind is kind and cfg.episodes == episodes
    if kind is MethodKind.PROMPTED:
        preset = "vanilla" if method == "r2po" else method
        assert cfg.mechanisms == registry.PRESETS[preset]
    else:
        assert not (cfg.mechanisms.encode_params or cfg.mechanisms.detailed_feedback or cfg.mechanisms.disclose_optimum)


def test_a_black_box_method_refuses_prompt_switches(capsys) -> None:  # type: ignore[no-untyped-def]
    assert get_method("cmaes").mechanisms(encode_params=True).encode_params
    code = main(["run", "--env", "CartPole", "--method", "cmaes", "--detailed-feedback", "on", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err == ("ppprops: error: --detailed-feedback does not apply to --method cmaes: it sends no prompt "
                                 "(only --encode-params does, choosing the space it searches)\n")  # fmt: skip
    with pytest.raises(ConfigError, match="only --encode-params applies"):
        replace(make_config("CartPole", "random"), mechanisms=resolve("pp")).validate()


def test_an_rl_baseline_or_an_unknown_method_is_not_a_search() -> None:
    with pytest.raises(ConfigError, match="ppprops baseline rl --algo ppo"):
        replace(make_config(), method="rl-ppo").validate()
    with pytest.raises(ConfigError, match="unknown method 'ppx'"):
        replace(make_config(), method="ppx").validate()
    with pytest.raises(ConfigError, match="unknown method 'ppo'.*RL baselines go in"):
        build_spec(flags_table(["CartPole"], ["ppo"], 1))


def test_a_method_added_to_the_registry_runs_everywhere(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The recipe for a new search method: a phase builder in strategies and one Method entry."""

    class Centre:
        def ask(self, iteration: int) -> Proposal:
            return Proposal(np.full(10, 0.5 * iteration), source="centre")

        def tell(self, candidate: object) -> None:
            pass

    monkeypatch.setattr(strategies, "centre_phase", lambda s: Phase("centre", Centre(), s.iterations), raising=False)
    monkeypatch.setitem(METHODS, "centre", Method("centre", MethodKind.BLACK_BOX, "the box centre, then steps", phase="centre_phase"))
    cfg = run_config(run_parser().parse_args(["--env", "CartPole", "--method", "centre", "--warmup", "2", "--iterations", "3",
                                              "--final-episodes", "1", "--select-top", "0"]))  # fmt: skip
    start(cfg, tmp_path / "r")
    store = open_store(tmp_path / "r")
    try:
        cands = store.candidates()
        assert [c.source for c in cands] == ["warmup", "warmup", "centre", "centre", "centre"]
        assert [float(c.params[0]) for c in cands[2:]] == [0.0, 0.5, 1.0]
        assert store.status() == "finished"
    finally:
        store.close()
    spec = build_spec(flags_table(["CartPole"], ["centre", "pp"], 1))
    assert [r.method for r in spec.runs] == ["centre", "pp"]


def test_status_and_kind_read_the_strings_stores_hold() -> None:
    assert RunStatus.parse("finished") == (RunStatus.FINISHED, "")
    assert RunStatus.parse("stopped: context overflow at LLM call 4") == (RunStatus.STOPPED, "context overflow at LLM call 4")
    assert RunStatus.parse("running") == (RunStatus.RUNNING, "")
    assert RunStatus.parse("something else")[0] is RunStatus.UNKNOWN
    assert RunStatus.STOPPED.stored("why") == "stopped: why" and RunStatus.FINISHED.stored() == "finished"
    assert is_complete("stopped: why", RunKind.SEARCH) and not is_complete("stopped: why", RunKind.RL)
    assert not is_complete("interrupted", RunKind.SEARCH) and is_complete("finished", RunKind.RL)
    assert RunKind.of_config({"kind": "rl", "algo": "ppo"}) is RunKind.RL
    assert RunKind.of_config(make_config().to_json()) is RunKind.SEARCH  # a search config has no "kind" key


def test_no_module_imports_private_names_of_the_cli() -> None:
    offenders = []
    for path in [*(ROOT / "src").rglob("*.py"), *(ROOT / "tests").glob("*.py"), *(ROOT / "benchmarks").glob("*.py")]:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and re.fullmatch(r"(ppprops\.)?cli", node.module.lstrip(".")):
                offenders += [f"{path.name}: {a.name}" for a in node.names if a.name.startswith("_")]
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "cli" and node.attr.startswith("_"):
                if path.name != "test_cli_manners.py":  # that test replaces a handler to simulate Ctrl-C in it
                    offenders.append(f"{path.name}: cli.{node.attr}")
    assert not offenders


def test_old_configs_read_back_with_every_switch(tmp_path: Path) -> None:
    old = make_config("CartPole", "vanilla").to_json()
    del old["mechanisms"]["describe_task"], old["mechanisms"]["encoded_warmup"]  # written before these switches existed
    back = RunConfig.from_json(old)
    assert back.mechanisms.describe_task is True and back.mechanisms.encoded_warmup is False


def test_a_grid_started_before_a_switch_existed_still_matches() -> None:
    from ppprops.experiments.grid import _same_config

    planned = build_spec(flags_table(["CartPole"], ["pp"], 1)).runs[0].config
    old = RunConfig.from_json(planned).to_json()
    del old["mechanisms"]["describe_task"]  # grid.json and run.sqlite written before --describe-task
    assert _same_config(old, planned)
    changed = RunConfig.from_json(planned).to_json()
    changed["mechanisms"]["describe_task"] = False
    assert not _same_config(changed, planned)
