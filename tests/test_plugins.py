"""Plugins: a method and an attack of an installed package are known in every process (``ppprops.plugins``).

The package is the one the recipes of docs/architecture.md describe: its modules are the page's
code blocks and its entry points the page's ``[project.entry-points."ppprops.plugins"]`` tables.
It is installed the way pip leaves a package in site-packages: a folder on ``PYTHONPATH`` holding
the modules and a ``<name>-0.1.dist-info`` with ``METADATA`` and ``entry_points.txt``. Every check
runs in a fresh interpreter, which registers nothing itself: only the entry points can tell it.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from ppprops.client.secrets import Secrets
from ppprops.runner import start

from support import doc_block, make_config, offline_llm

DOC = (Path(__file__).resolve().parents[1] / "docs" / "architecture.md").read_text(encoding="utf-8")
SMALL = ["--warmup", "3", "--iterations", "3", "--final-episodes", "2", "--select-top", "0", "--seed", "1"]

# A second plugin, in the "module:function" form: the function registers a method when called.
HALVE = '''
from my_ppprops.shrink import Shrink  # the recipe's proposer (importing it registers shrink, once)
from ppprops.loop import Phase
from ppprops.methods import Method, MethodKind, register_method

CALLS = []


def register():
    CALLS.append(1)
    register_method(Method("halve", MethodKind.BLACK_BOX, "shrink, under another name", iteration_unit="samples",
                           phase=lambda s: Phase("halve", Shrink(s.task.D, s.box), s.iterations)))
'''

BROKEN = """
import pathlib

with open(pathlib.Path(__file__).with_name("imports.txt"), "a") as f:  # one x per import
    f.write("x")
raise ImportError("needs the frobnicate package")
"""

# Read back in a new process through the Python API: the sources, parameters and returns of every candidate.
LOAD_RUN = ("import json, sys, ppprops; r = ppprops.load_run(sys.argv[1]); "
            "print(json.dumps({'status': r.status, 'method': r.config.method, 'sources': [c.source for c in r.history], "
            "'params': [c.params.tolist() for c in r.history], 'returns': [c.ret for c in r.history]}))")  # fmt: skip


def _install(root: Path, name: str, entry_points: dict[str, str]) -> None:
    """What ``pip install`` leaves for a distribution ``name`` declaring ``entry_points`` in ``ppprops.plugins``."""
    info = root / f"{name.replace('-', '_')}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[ppprops.plugins]\n" + "".join(f"{k} = {v}\n" for k, v in entry_points.items()))


def _doc_entry_points() -> dict[str, str]:
    """The entry points of every ``pyproject.toml`` table the page shows."""
    found: dict[str, str] = {}
    for block in re.findall(r"```toml\n(.*?)```", DOC, flags=re.S):
        table = tomllib.loads(block).get("project", {}).get("entry-points", {}).get("ppprops.plugins")
        if table:
            found.update(table)
    return found


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The recipes' package ``my-ppprops`` (method ``shrink``, attack ``return-per-step``) and ``toy-halve``."""
    root = tmp_path_factory.mktemp("site")
    pkg = root / "my_ppprops"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "shrink.py").write_text(doc_block(DOC, "# my_ppprops/shrink.py"))
    (pkg / "attacks.py").write_text(doc_block(DOC, "# my_ppprops/attacks.py"))
    eps = _doc_entry_points()
    assert eps == {"shrink": "my_ppprops.shrink", "return-per-step": "my_ppprops.attacks"}
    _install(root, "my-ppprops", eps)
    (root / "toy_halve.py").write_text(HALVE)
    _install(root, "toy-halve", {"halve": "toy_halve:register"})
    return root


@pytest.fixture(scope="module")
def broken_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A distribution ``broken-plugin`` whose plugin module raises ImportError when imported."""
    root = tmp_path_factory.mktemp("broken")
    (root / "broken_plugin.py").write_text(BROKEN)
    _install(root, "broken-plugin", {"broken": "broken_plugin"})
    return root


def _python(args: list[str], *sites: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``python ARGS`` in a fresh interpreter with ``sites`` on its path (the installed plugins)."""
    path = os.pathsep.join([*map(str, sites), *filter(None, [os.environ.get("PYTHONPATH")])])
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd, timeout=600,
                          env={**os.environ, "PYTHONPATH": path})  # fmt: skip


def _load_run(run: Path, site: Path) -> dict:  # type: ignore[type-arg]
    res = _python(["-c", LOAD_RUN, str(run)], site, cwd=run.parent)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout)  # type: ignore[no-any-return]


def _assert_shrink_history(run: dict, warmup: int, iterations: int) -> None:  # type: ignore[type-arg]
    """The candidates of a shrink run: the warm-up, then each ask half the best candidate before it."""
    assert run["status"] == "finished" and run["method"] == "shrink"
    assert run["sources"] == ["warmup"] * warmup + ["shrink"] * iterations
    params, returns = np.array(run["params"]), run["returns"]
    for i in range(warmup, warmup + iterations):
        best = int(np.argmax(returns[:i]))  # ties: the first, as Shrink.tell keeps it
        np.testing.assert_allclose(params[i], np.clip(0.5 * params[best], -6.0, 6.0))


def test_a_plugin_method_runs_from_the_shell_and_reads_back_in_new_processes(site: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    res = _python(["-m", "ppprops", "run", "--env", "CartPole", "--method", "shrink", *SMALL, "--out", str(run), "--quiet"],
                  site, cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    _assert_shrink_history(_load_run(run, site), 3, 3)
    show = _python(["-m", "ppprops", "show", str(run)], site, cwd=tmp_path)
    assert show.returncode == 0, show.stderr[-2000:]
    assert "method shrink" in show.stdout and "6 (3 warmup, 3 shrink)" in show.stdout
    audit = _python(["-m", "ppprops", "audit", str(run)], site, cwd=tmp_path)
    assert audit.returncode == 0 and "(method shrink): 0 requests" in audit.stdout, audit.stderr[-2000:]
    # --help lists the plugin's method among the choices
    helped = _python(["-m", "ppprops", "run", "--help"], site, cwd=tmp_path)
    assert re.search(r"one of: vanilla,.*cmaes, shrink, halve\)", " ".join(helped.stdout.split()))


def test_a_plugin_method_runs_in_an_experiment_grid(site: Path, tmp_path: Path) -> None:
    spec = tmp_path / "toy.toml"
    spec.write_text('name = "toy"\nseeds = 1\n\n[run]\nwarmup = 3\niterations = 3\nfinal-episodes = 2\nselect-top = 0\n\n'
                    '[[grid]]\ntasks = ["CartPole"]\nmethods = ["shrink"]\n')  # fmt: skip
    grid = tmp_path / "grid"
    res = _python(["-m", "ppprops", "experiment", str(spec), "--out", str(grid), "--jobs", "1"], site, cwd=tmp_path)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    # the run went through a fresh interpreter of execute_local, which found the method by its entry point
    _assert_shrink_history(_load_run(grid / "runs" / "CartPole__shrink__0", site), 3, 3)


def test_a_plugin_attack_is_in_the_privacy_report_of_a_new_process(site: Path, tmp_path: Path) -> None:
    # a pp run in the chat form, which shows CartPole's episode length beside each scaled return
    secrets = Secrets(run_id="plugin", a=np.exp(np.random.default_rng(0).uniform(-2.3, 2.3, 10)), c=3.7)
    with offline_llm():
        start(make_config("CartPole", "pp", warmup=6, iterations=2, final_episodes=0, seed=0), tmp_path / "runs" / "pp", secrets=secrets)
    res = _python(["-m", "ppprops", "privacy-report", "--runs", str(tmp_path / "runs"), "--json"], site, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    (analysis,) = json.loads(res.stdout)
    # the plugin's attack ran in that process: c = printed return / episode length, to the printed rounding
    assert analysis["applicable"]["return-per-step"] and analysis["errors"]["return-per-step"] < 0.01
    assert "| return-per-step | c |" in (tmp_path / "runs" / "privacy-report.md").read_text()


def test_plugins_load_once_and_only_when_a_name_is_missing(site: Path, tmp_path: Path) -> None:
    script = """
import json, sys
from ppprops import methods
from ppprops.cli import run_config, run_parser
from ppprops.privacy import attacks
seen = {}
cfg = run_config(run_parser().parse_args(["--env", "CartPole", "--method", "pp"]))
seen["after_builtin"] = sorted(m for m in ("my_ppprops.shrink", "toy_halve") if m in sys.modules)
seen["halve"] = methods.get_method("halve").title
seen["after_miss"] = sorted(m for m in ("my_ppprops.shrink", "toy_halve") if m in sys.modules)
seen["attack"] = attacks.TARGET.get("return-per-step")
seen["unknown"] = methods.find_method("nope")
import toy_halve
seen["calls"] = len(toy_halve.CALLS)
print(json.dumps(seen))
"""
    res = _python(["-c", script], site, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout) == {"after_builtin": [], "halve": "shrink, under another name",
                                      "after_miss": ["my_ppprops.shrink", "toy_halve"], "attack": "c", "unknown": None,
                                      "calls": 1}  # fmt: skip


def test_a_broken_plugin_is_one_line_and_exit_2(site: Path, broken_site: Path, tmp_path: Path) -> None:
    line = ("ppprops: error: plugin 'broken' = 'broken_plugin' (entry point group 'ppprops.plugins' of broken-plugin 0.1) "
            "failed to load: ImportError: needs the frobnicate package; fix it or uninstall broken-plugin\n")  # fmt: skip
    run = ["-m", "ppprops", "run", "--env", "CartPole", *SMALL]
    res = _python([*run, "--method", "shrink", "--out", str(tmp_path / "a")], broken_site, site, cwd=tmp_path)
    assert (res.returncode, res.stderr) == (2, line)
    assert not (tmp_path / "a").exists()
    grid = _python(["-m", "ppprops", "experiment", "--tasks", "CartPole", "--methods", "shrink", "--seeds", "1", *SMALL[:6],
                    "--out", str(tmp_path / "g")], broken_site, site, cwd=tmp_path)  # fmt: skip
    assert (grid.returncode, grid.stderr) == (2, line)
    # a built-in method never reads the plugins: the broken one is not in the way
    ok = _python([*run, "--method", "random", "--out", str(tmp_path / "b"), "--quiet"], broken_site, cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr[-2000:]
    # the Python API: the same ConfigError, and again on the next miss (the plugin is not imported twice)
    script = """
from ppprops.errors import ConfigError
from ppprops.methods import get_method
for name in ("shrink", "nope"):
    try:
        get_method(name)
    except ConfigError as e:
        print(e)
"""
    imports = broken_site / "imports.txt"
    before = len(imports.read_text())
    api = _python(["-c", script], broken_site, site, cwd=tmp_path)
    assert api.returncode == 0 and api.stdout == 2 * line.removeprefix("ppprops: error: ")
    assert len(imports.read_text()) == before + 1
