"""`ppprops report` turns a grid into correct tables (checked against the stores), curves, history-cost
plots and an index.html that renders in headless Chromium with every table and image."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.errors import MissingExtraError
from ppprops.experiments.report import write_report
from ppprops.experiments.run_grid import run_grid
from ppprops.experiments.spec import build_spec
from ppprops.testing.fault_server import FaultConfig, FaultServer

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
REQUIRE_CHROMIUM = "PPPROPS_REQUIRE_CHROMIUM"  # set by .ci/run: a missing browser fails the test instead of skipping it
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]  # fmt: skip


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """CartPole: vanilla at K=10 and unbounded, pp, and random search, two seeds, against a local
    OpenAI-compatible server that answers valid random vectors (fast, no model needed)."""
    out = tmp_path_factory.mktemp("report") / "grid"
    with FaultServer(FaultConfig(fault_rate=0.0, seed=1)) as server:
        raw = {
            "name": "report-test", "seeds": 2,
            "run": {"warmup": 3, "iterations": 4, "final-episodes": 2, "base-url": server.base_url, "model": "synthetic",
                    "retries": 0},
            "grid": [
                {"tasks": ["CartPole"], "methods": ["vanilla", "pp"], "label": "K10", "run": {"top-k": 10}},
                {"tasks": ["CartPole"], "methods": ["vanilla"], "label": "unbounded", "run": {"top-k": 0}},
                {"tasks": ["CartPole"], "methods": ["random"]},
            ],
        }  # fmt: skip
        result = run_grid(build_spec(raw, source="test"), out, log=lambda s: None)
    assert result.ok, [o.error for o in result.outcomes]
    yield out


def _best(run_dir: Path) -> float:
    with sqlite3.connect(run_dir / "run.sqlite") as con:
        return max(json.loads(r[0])["return"] for r in con.execute("SELECT feedback FROM candidates WHERE reevaluates IS NULL"))


def _final(run_dir: Path) -> float:
    with sqlite3.connect(run_dir / "run.sqlite") as con:
        return float(np.mean(json.loads(con.execute("SELECT returns FROM final_eval").fetchone()[0])))


def test_report_tables_hold_the_runs_numbers(grid: Path) -> None:
    assert main(["report", str(grid)]) == 0
    out = grid / "report"
    for stem in ("main_results", "bounded_history", "history_cost", "baselines"):
        for ext in ("md", "csv", "tex"):
            assert (out / f"{stem}.{ext}").stat().st_size > 0, f"{stem}.{ext}"
    assert (out / "curves_CartPole.png").exists() and (out / "history_cost_CartPole.png").exists()
    rows = {r["column"]: r for r in csv.DictReader(open(out / "main_results.csv"))}
    assert set(rows) == {"vanilla", "vanilla (unbounded)", "pp"}
    runs = grid / "runs"
    for column, stem in (("vanilla", "vanilla-K10"), ("vanilla (unbounded)", "vanilla-unbounded"), ("pp", "pp-K10")):
        bests = [_best(runs / f"CartPole__{stem}__{s}") for s in (0, 1)]
        finals = [_final(runs / f"CartPole__{stem}__{s}") for s in (0, 1)]
        assert float(rows[column]["best_mean"]) == pytest.approx(np.mean(bests))
        assert float(rows[column]["best_std"]) == pytest.approx(np.std(bests))
        assert float(rows[column]["final_mean"]) == pytest.approx(np.mean(finals))
        assert rows[column]["n"] == "2"
    assert rows["pp"]["paper_mean"] == "499.9" and rows["pp"]["paper_table"] == "tab:all_results"
    assert rows["vanilla (unbounded)"]["paper_mean"] == ""  # the paper's unbounded runs are Ant only
    top = max(float(r["best_mean"]) for r in rows.values())
    assert [r["column"] for r in rows.values() if r["bold"] == "1"] == [c for c, r in rows.items() if float(r["best_mean"]) == top]
    md = (out / "main_results.md").read_text()
    assert f"**{top:.2f} (" in md and "499.9 (0.2)" in md
    tex = (out / "main_results.tex").read_text()
    assert r"\textbf{" in tex and r"\toprule" in tex and "tab:ppprops_main_results" in tex

    b = next(csv.DictReader(open(out / "bounded_history.csv")))
    k10, unb = float(b["k10_mean"]), float(b["unbounded_mean"])
    assert float(b["diff_pct"]) == pytest.approx((k10 - unb) / abs(unb) * 100)
    cost = next(csv.DictReader(open(out / "history_cost.csv")))
    # the final prompt size is the last LLM call's, averaged over the seeds
    with sqlite3.connect(runs / "CartPole__vanilla-unbounded__0" / "run.sqlite") as con:
        last = con.execute("SELECT prompt_chars FROM llm_calls ORDER BY id DESC LIMIT 1").fetchone()[0]
    with sqlite3.connect(runs / "CartPole__vanilla-unbounded__1" / "run.sqlite") as con:
        last2 = con.execute("SELECT prompt_chars FROM llm_calls ORDER BY id DESC LIMIT 1").fetchone()[0]
    assert float(cost["final_prompt_chars_unbounded"]) == pytest.approx((last + last2) / 2)
    base = {r["column"]: r for r in csv.DictReader(open(out / "baselines.csv"))}
    assert float(base["random"]["score_mean"]) == pytest.approx(np.mean([_best(runs / f"CartPole__random__{s}") for s in (0, 1)]))
    runs_csv = list(csv.DictReader(open(out / "runs.csv")))
    assert len(runs_csv) == 8 and all(r["status"] == "finished" for r in runs_csv)


def test_reward_curve_mean_and_band_are_over_seeds(grid: Path) -> None:
    from ppprops.experiments.plots import curve
    from ppprops.experiments.report import read_run
    from ppprops.rundir import find_runs

    recs = [read_run(p) for p in find_runs(grid) if "pp-K10" in p.name]
    x, mean, std = curve(recs)
    assert list(x) == list(range(-3, 4))  # warm-up drawn before iteration 0
    ys = np.array([r.returns for r in recs], dtype=float)
    np.testing.assert_allclose(mean, ys.mean(axis=0))
    np.testing.assert_allclose(std, ys.std(axis=0))


def _chromium() -> str:
    """The browser for the report page test: where it is missing, a skip with the reason, or a
    failure when ``REQUIRE_CHROMIUM`` is set (``.ci/run`` sets it: CI must not skip this test)."""
    if Path(CHROMIUM).exists():
        return CHROMIUM
    why = f"chromium is not installed ({CHROMIUM} is absent; .ci/run installs it)"
    if os.environ.get(REQUIRE_CHROMIUM):
        pytest.fail(f"{why}, and {REQUIRE_CHROMIUM} is set: the report page must be tested here")
    pytest.skip(why)


def test_a_missing_chromium_skips_for_a_developer_and_fails_where_ci_requires_it(monkeypatch: pytest.MonkeyPatch,
                                                                                 tmp_path: Path) -> None:
    monkeypatch.setattr(sys.modules[__name__], "CHROMIUM", str(tmp_path / "no-chromium"))
    monkeypatch.delenv(REQUIRE_CHROMIUM, raising=False)
    with pytest.raises(pytest.skip.Exception, match="chromium is not installed"):
        _chromium()
    monkeypatch.setenv(REQUIRE_CHROMIUM, "1")
    with pytest.raises(pytest.fail.Exception, match=f"{REQUIRE_CHROMIUM} is set"):
        _chromium()


def test_ci_stops_when_chromium_cannot_be_installed(tmp_path: Path) -> None:
    """The chromium block of .ci/run, with no chromium on the PATH and an apt-get that fails."""
    script = (Path(__file__).resolve().parent.parent / ".ci" / "run").read_text()
    block = script[script.index("# chromium: begin"):script.index("# chromium: end")]
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "apt-get").write_text("#!/bin/sh\nexit 100\n")
    (bin_dir / "apt-get").chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin/nonexistent", "HOME": str(tmp_path)}
    done = subprocess.run(["/bin/bash", "-c", "set -euo pipefail\n" + block + "echo reached"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and "reached" not in done.stdout
    assert "ci: chromium could not be installed" in done.stderr
    (bin_dir / "chromium").write_text("#!/bin/sh\nexit 0\n")  # with a browser there, CI requires the test
    (bin_dir / "chromium").chmod(0o755)
    done = subprocess.run(["/bin/bash", "-c", "set -euo pipefail\n" + block + 'echo "required=$PPPROPS_REQUIRE_CHROMIUM"'],
                          env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "required=1" and REQUIRE_CHROMIUM == "PPPROPS_REQUIRE_CHROMIUM"


def test_index_html_renders_tables_and_images_in_chromium(grid: Path, tmp_path: Path) -> None:
    browser = _chromium()
    out = write_report(grid, tmp_path / "report")
    url = (out / "index.html").as_uri()
    dom = subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'ud1'}", "--virtual-time-budget=10000",
                          "--dump-dom", url], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert dom.returncode == 0, dom.stderr[-2000:]
    body = re.search(r"<body[^>]*>", dom.stdout)
    assert body is not None
    loaded = re.search(r'data-images-loaded="(\d+)"', body.group(0))
    total = re.search(r'data-images-total="(\d+)"', body.group(0))
    assert loaded and total, "the page script did not run"
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert int(total.group(1)) == len(pngs) >= 2 and loaded.group(1) == total.group(1)
    for key in ("main_results", "bounded_history", "history_cost", "baselines", "runs"):
        assert f'data-table="{key}"' in dom.stdout
    rows = {r["column"]: r for r in csv.DictReader(open(out / "main_results.csv"))}
    assert f"{float(rows['pp']['best_mean']):.2f} (" in dom.stdout  # the numbers are in the rendered table

    shot = tmp_path / "shot.png"
    run = subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'ud2'}", "--virtual-time-budget=10000",
                          "--hide-scrollbars", "--window-size=1280,2400", f"--screenshot={shot}", url],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0 and shot.exists(), run.stderr[-2000:]
    import matplotlib.image

    pixels = matplotlib.image.imread(shot)[..., :3].reshape(-1, 3)
    colours = np.unique((pixels * 255).astype(np.uint8), axis=0)
    assert len(colours) > 50  # text, table borders and plot colours: not a blank page
    white = np.all(pixels > 0.97, axis=1).mean()
    assert 0.2 < white < 0.995


def test_report_without_matplotlib_names_the_extra(grid: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if the report extra were not installed
    with pytest.raises(MissingExtraError, match=r"ppprops\[report\]"):
        write_report(grid)


def test_report_of_a_folder_without_runs_is_an_input_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path)]) == 2
    assert "holds no run directories" in capsys.readouterr().err
