"""Transcript-only attacks: they recover the paper's secrets, and learn nothing beyond the prior
against pp-hardened. Runs use the real loop, tasks and codec with an offline stand-in for the LLM
(``EchoOptimizer``), and seeded secrets drawn from each scheme's own distribution."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.client.secrets import HARDENED_A_LOG, HARDENED_P_LOG, LOG_HIGH, LOG_LOW, Secrets
from ppprops.methods import resolve
from ppprops.privacy.attacks import run_attacks
from ppprops.privacy.audit import run_grid_factor, search_config
from ppprops.privacy.matrix import analyse_run, privacy_report
from ppprops.privacy.requests import load_requests
from ppprops.privacy.simfit import SimLimits
from ppprops.rundir import open_run
from ppprops.runner import start
from ppprops.tasks import get_task

from support import make_config, offline_llm


def seeded_secrets(method: str, task: str, seed: int) -> Secrets:
    """The scheme's secret distribution (see client/secrets.py), from a seeded generator so tests repeat."""
    D = get_task(task).D
    rng = np.random.default_rng(1000 + seed)
    c = float(np.exp(rng.uniform(LOG_LOW, LOG_HIGH)))
    if method == "pp":
        return Secrets(run_id=f"{task}-{method}-{seed}", a=np.exp(rng.uniform(LOG_LOW, LOG_HIGH, D)), c=c)
    p = float(np.exp(rng.choice([-1, 1]) * rng.uniform(*HARDENED_P_LOG)))
    return Secrets(run_id=f"{task}-{method}-{seed}", a=np.exp(rng.uniform(*HARDENED_A_LOG, D)), c=c, m=rng.uniform(-3, 3, D),
                   s=float(rng.uniform(-500, 500)), p=p)


def simulate(root: Path, task: str, method: str, seed: int, iterations: int = 10) -> Path:
    out = root / f"{task}__{method}__{seed}"
    # pp-hardened paced: the request times of an in-process run follow its episodes' steps (the timing
    # channel, tests/test_timing_channel.py), and these tests are about what the transcript itself says
    config = make_config(task, method, warmup=10, iterations=iterations, final_episodes=0, seed=seed,
                         mechanisms=resolve(method, pace_requests=method == "pp-hardened"))
    with offline_llm():
        start(config, out, secrets=seeded_secrets(method, task, seed))
    return out


def _errors(run: Path, task: str, method: str, seed: int) -> dict[str, float]:
    s = seeded_secrets(method, task, seed)
    with open_run(run) as r:  # on the grid, what decoding needs (and attacks estimate) is g a_j
        g = run_grid_factor(search_config(r.stored, run), s)
    out = {}
    for e in run_attacks(load_requests(run), task, (-6.0, 6.0), simulate=False):
        if not e.applicable:
            continue
        v = np.asarray(e.value, dtype=np.float64)
        true = s.c if e.target == "c" else g * s.a
        err = np.abs(v / true - 1)
        out[e.attack] = float(np.nanmedian(err))
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str, int], Path]:
    root = tmp_path_factory.mktemp("attacks")
    todo = [("CartPole", "pp", s) for s in range(3)] + [("Acrobot", "pp", 0)] + [("CartPole", "pp-hardened", s) for s in range(6)]
    return {(t, m, s): simulate(root, t, m, s) for t, m, s in todo}


def test_paper_secrets_fall_on_cartpole(runs: dict[tuple[str, str, int], Path]) -> None:
    for seed in range(3):
        err = _errors(runs["CartPole", "pp", seed], "CartPole", "pp", seed)
        assert err["diagnostic"] < 0.01  # c = printed return / episode_length
        assert "seed-replay" not in err  # the warm-up is keyed by the secrets: the run seed replays nothing
        assert err["warmup-range"] < 0.5  # a_j ~ max|theta~_j| / 6: the right order, not exact
        if "lattice" in err:
            assert err["lattice"] < 0.01


def test_paper_secrets_fall_on_acrobot(runs: dict[tuple[str, str, int], Path]) -> None:
    err = _errors(runs["Acrobot", "pp", 0], "Acrobot", "pp", 0)
    assert err["diagnostic"] < 0.01  # return = -episode_length + success
    assert err["known-cap"] < 0.01  # success=0 means -500
    assert "seed-replay" not in err


def test_hardened_secrets_hold_against_every_transcript_attack(runs: dict[tuple[str, str, int], Path]) -> None:
    """Per attack that reads the transcript alone (no simulator: those are tests/test_simulator_attacks.py),
    the median error over runs is no better than the prior guess (c = a_j = 1)."""
    analyses = [analyse_run(runs["CartPole", "pp-hardened", s], simulate=False) for s in range(6)]
    prior_c = float(np.median([a.errors["prior (c)"] for a in analyses]))
    prior_a = float(np.median([a.errors["prior (a)"] for a in analyses]))
    for name in ("diagnostic", "lattice", "known-cap"):
        assert float(np.median([a.errors[name] for a in analyses])) >= 0.9 * prior_c, name
    for name in ("warmup-range", "stated-range", "clip-edge", "seed-replay"):
        assert float(np.median([a.errors[name] for a in analyses])) >= 0.8 * prior_a, name
    for a in analyses:
        assert not a.applicable["diagnostic"]
        # c is never recovered to within 5%, nor A by replaying the warm-up
        assert all(a.errors[k] > 0.05 for k in ("diagnostic", "lattice", "known-cap", "seed-replay")), a.errors
        assert a.audit.startswith("CLEAN")


def test_the_attacks_only_read_the_transcript(runs: dict[tuple[str, str, int], Path], tmp_path: Path) -> None:
    """Moving the key file and the candidates away changes nothing: the estimate comes from the requests alone."""
    run = runs["CartPole", "pp", 0]
    requests = load_requests(run)
    blind = [dict(r.__dict__) for r in requests]
    assert all("secrets" not in json.dumps({k: str(v) for k, v in b.items()}) for b in blind)
    first = {e.attack: e.value for e in run_attacks(requests, "CartPole", (-6.0, 6.0), simulate=False)}
    again = {e.attack: e.value for e in run_attacks(load_requests(run), "CartPole", (-6.0, 6.0), simulate=False)}
    assert math.isclose(float(first["diagnostic"]), float(again["diagnostic"]))  # type: ignore[arg-type]


def test_privacy_report_table_and_command(runs: dict[tuple[str, str, int], Path], tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    small = SimLimits(vector_steps=1_000_000, env_steps=5_000)
    text, analyses = privacy_report([runs["CartPole", "pp", 0], runs["CartPole", "pp-hardened", 0]], small)
    assert "| CartPole pp | CartPole pp-hardened, paced |" in text  # these pp-hardened runs pace their requests
    for row in ("diagnostic", "lattice", "known-cap", "warmup-range", "stated-range", "clip-edge", "seed-replay", "sim-exact",
                "sim-exact-a", "sim-marginal", "sim-marginal-lattice", "sim-marginal-a", "raw return (sim-exact)", "prior (c)"):
        assert f"| {row} |" in text
    assert re.search(r"\| diagnostic \| c \| [^|]*% \(1/1\) \| [^|]*% \(0/1\) \|", text)  # k/n: runs within 1%
    assert "Simulator attacks are bounded by 1e+06 simulated steps" in text
    assert "| CartPole | pp-hardened, paced | 1 | 10 + 10 |" in text
    root = runs["CartPole", "pp", 0].parent
    assert main(["privacy-report", "--runs", str(root), "--no-simulate"]) == 0
    assert "| Acrobot pp |" in capsys.readouterr().out
    assert (root / "privacy-report.md").exists() and len(json.loads((root / "privacy-report.json").read_text())) == len(runs)
    assert main(["privacy-report", "--runs", str(tmp_path)]) == 2  # no runs there: one line, exit 2
    capsys.readouterr()
    assert main(["privacy-report", "--runs", str(root), "--pace-requests"]) == 2  # a setting of new runs only
    assert capsys.readouterr().err == ("ppprops: error: --pace-requests is a setting of new runs; the runs under --runs were made as "
                                       "they were\n")
    assert main(["privacy-report", "--runs", str(root), "--number-format", "grid"]) == 2
    assert capsys.readouterr().err == ("ppprops: error: --number-format is a setting of new runs; the runs under --runs were made as "
                                       "they were\n")


def test_privacy_report_runs_a_users_task_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A user's own robot (a private module env) gets the same matrix: the simulator attacks say why they did not run."""
    task_file = Path(__file__).resolve().parents[1] / "examples" / "own_robot" / "point_robot.toml"
    out = tmp_path / "own"
    assert main(["privacy-report", "--offline", "--task-file", str(task_file), "--seeds", "1", "--warmup", "3",
                 "--iterations", "2", "--final-episodes", "1", "--out", str(out), "--number-format", "grid", "--json"]) == 0  # fmt: skip
    analyses = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["PointRobot__pp-hardened__0", "PointRobot__pp__0"]
    for d in out.iterdir():
        if d.is_dir():  # both schemes wrote the grid the flag asked for
            with open_run(d) as run:
                assert run.config.number_format == "grid"
    assert len(analyses) == 2
    for a in analyses:
        assert a["not_run"]["sim-exact"] == "the env of task PointRobot is private (its dynamics cannot be simulated by the provider)"
    assert main(["privacy-report", "--envs", "", "--out", str(tmp_path / "none")]) == 2
    assert "names no task" in capsys.readouterr().err
    assert main(["privacy-report", "--task-file", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "none")]) == 2
    assert not (tmp_path / "none").exists()
