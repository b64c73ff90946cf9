"""The recipes of docs/architecture.md, followed as written: a toy method, a toy task, a toy attack.

Each test runs the code the page shows (its code blocks, written to the files they name), then
asserts what the recipe promises in this process: the method runs through the loop, the task file
is searched, the attack appears in the privacy report with its error scored. The same modules
declared as ``ppprops.plugins`` entry points, in fresh processes: tests/test_plugins.py.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

import ppprops
from ppprops.cli import main
from ppprops.client.secrets import Secrets
from ppprops.errors import ConfigError
from ppprops.methods import METHODS, Method, register_method
from ppprops.privacy import attacks
from ppprops.privacy.attacks import register_attack
from ppprops.privacy.matrix import privacy_report
from ppprops.runner import start

from support import doc_block, make_config, offline_llm

DOC = (Path(__file__).resolve().parents[1] / "docs" / "architecture.md").read_text(encoding="utf-8")


def _in_doc(*snippets: str) -> None:
    for s in snippets:
        assert s in DOC, f"docs/architecture.md no longer shows: {s}"


@contextmanager
def _import_doc_module(root: Path, monkeypatch: pytest.MonkeyPatch, name: str) -> Iterator[ModuleType]:
    """Write the page's block ``# my_ppprops/<name>.py`` into a package under ``root``, import it, and
    forget the package afterwards (so the next test imports it afresh)."""
    pkg = root / "my_ppprops"
    pkg.mkdir(parents=True, exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / f"{name}.py").write_text(doc_block(DOC, f"# my_ppprops/{name}.py"))
    monkeypatch.syspath_prepend(str(root))
    try:
        yield importlib.import_module(f"my_ppprops.{name}")
    finally:
        for mod in ("my_ppprops", f"my_ppprops.{name}"):
            sys.modules.pop(mod, None)


# -- add a method ----------------------------------------------------------------------------
@pytest.fixture
def shrink_method(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Method]:
    assert "shrink" not in METHODS
    try:
        with _import_doc_module(tmp_path / "src", monkeypatch, "shrink"):  # registers "shrink" on import
            yield METHODS["shrink"]
    finally:
        METHODS.pop("shrink", None)


def test_recipe_add_a_method(shrink_method: Method, tmp_path: Path) -> None:
    _in_doc('ppprops.search(task, method="shrink")', '[project.entry-points."ppprops.plugins"]\nshrink = "my_ppprops.shrink"')
    result = ppprops.search("CartPole", method="shrink", warmup=4, iterations=3, evaluation={"final_episodes": 0, "select_top": 0}, seed=1, out=tmp_path / "r")
    assert result.status == "finished"
    sources = [c.source for c in result.history]
    assert sources == ["warmup"] * 4 + ["shrink"] * 3
    # each shrink candidate is half the best candidate before it (clipped to the box)
    for i in range(4, 7):
        before = result.history[:i]
        best = max(before, key=lambda c: c.ret)  # ties: the first, as Shrink.tell keeps it
        np.testing.assert_allclose(result.history[i].params, np.clip(0.5 * best.params, -6.0, 6.0))
    # ppprops run --method shrink in the same process (the CLI's main, not a shell)
    out = tmp_path / "cli"
    code = main(["run", "--env", "CartPole", "--method", "shrink", "--warmup", "2", "--iterations", "2",
                             "--final-episodes", "0", "--select-top", "0", "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 0 and [c.source for c in ppprops.load_run(out).history] == ["warmup"] * 2 + ["shrink"] * 2
    with pytest.raises(ConfigError, match="already registered"):
        register_method(shrink_method)


# -- add a task ------------------------------------------------------------------------------


def test_recipe_add_a_task(tmp_path: Path) -> None:
    start_, end = DOC.index("# drift.toml, next to drift_env.py"), DOC.index("```", DOC.index("# drift.toml"))
    toml = DOC[start_:end]  # the task file exactly as the doc shows it
    _in_doc('ppprops.search("drift.toml", method="random")')
    (tmp_path / "drift_env.py").write_text(doc_block(DOC, "# drift_env.py, next to drift.toml"))  # the env the page shows
    (tmp_path / "drift.toml").write_text(toml)
    result = ppprops.search(tmp_path / "drift.toml", method="random", warmup=3, iterations=4, evaluation={"final_episodes": 2, "select_top": 0},
                            seed=0, out=tmp_path / "run")  # fmt: skip
    assert result.status == "finished" and result.task == "Drift"
    assert [c.source for c in result.history] == ["warmup"] * 3 + ["random"] * 4
    assert all(c.params.shape == (4,) for c in result.history)  # D = (n_s + 1) n_a = (1 + 1) * 2
    for c in result.history:  # 20 steps of -|x| with |x| <= 1 + 20 * 0.1: the return lies in [-60, 0]
        assert -60.0 <= c.ret <= 0.0
        assert c.feedback.diagnostics["episode_length"] == 20.0  # the file's time limit, never terminated early
        assert 0.0 <= float(c.feedback.diagnostics["distance"]) <= 3.0  # the declared diagnostic, read from info
    assert result.best_return == max(c.ret for c in result.history)
    assert result.final is not None and len(result.final.returns) == 2
    assert result.config.task_spec is not None and result.config.task_spec["name"] == "Drift"


# -- add a privacy attack --------------------------------------------------------------------
@pytest.fixture
def toy_attack(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    assert "return-per-step" not in attacks.ATTACKS
    try:
        with _import_doc_module(tmp_path / "src", monkeypatch, "attacks") as module:  # registers "return-per-step" on import
            yield module
    finally:
        attacks.ATTACKS.pop("return-per-step", None)
        attacks.TARGET.pop("return-per-step", None)


def test_recipe_add_a_privacy_attack(toy_attack: ModuleType, tmp_path: Path) -> None:
    _in_doc('[project.entry-points."ppprops.plugins"]\nreturn-per-step = "my_ppprops.attacks"')
    assert attacks.TARGET["return-per-step"] == "c" and attacks.ATTACKS["return-per-step"] is toy_attack.return_per_step
    c = 3.7
    secrets = Secrets(run_id="recipe", a=np.exp(np.random.default_rng(0).uniform(-2.3, 2.3, 10)), c=c)
    out = tmp_path / "run"
    with offline_llm():
        start(make_config("CartPole", "pp", warmup=6, iterations=3, final_episodes=0, seed=0), out, secrets=secrets)
    text, analyses = privacy_report([out])
    assert "| return-per-step | c |" in text
    err = analyses[0].errors["return-per-step"]
    assert analyses[0].applicable["return-per-step"]
    # CartPole's return is its episode length, so the estimate is c up to the printed rounding
    assert err < 0.01
    # the same error type as register_method's
    with pytest.raises(ConfigError, match="already registered"):
        register_attack("return-per-step", "c", toy_attack.return_per_step)
    with pytest.raises(ConfigError, match="'c' or 'a'"):
        register_attack("other", "x", toy_attack.return_per_step)
    assert "other" not in attacks.ATTACKS
