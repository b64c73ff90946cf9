"""The attack side: an attacker who can build a public env fits the secrets by simulating it.

One test per finding that failed on the code before: (1) the run seed is read off a pp-hardened
transcript and the audit warns; (2) with the initial states known, the exact fit recovers a
Pendulum-v1 pp-hardened run and the audit says EXPOSED; (3) without them, the marginal fit moves
the estimate of c from the prior towards the truth on CartPole pp-hardened, and the audit reports
it; (4) the audit is not CLEAN on a run the fit breaks and lists the attacks it could not run, with
why; (5) a module or class name of the user's own env in a prompt is flagged. Runs use the real
loop, tasks and codec with the offline stand-in optimizer, seeded secrets, and small simulation
budgets (``SMALL``), so the whole file takes seconds.
"""

from __future__ import annotations

import dataclasses
import sqlite3
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_attacks import seeded_secrets

from ppprops.cli import build_parser
from ppprops.client.secrets import Secrets
from ppprops.errors import ConfigError
from ppprops.privacy import simfit
from ppprops.privacy.attacks import run_attacks
from ppprops.privacy.audit import audit_run
from ppprops.privacy.commands import _limits
from ppprops.privacy.requests import load_requests
from ppprops.privacy.runseed import find_run_seed
from ppprops.privacy.simulator import Budget, EnvSim, OverBudget, env_is_public, simulator_for
from ppprops.privacy.view import view_of
from ppprops.runner import start
from ppprops.study import Study
from ppprops.tasks import get_task

from support import make_config, offline_llm, tamper_call

SMALL = simfit.SimLimits(vector_steps=3_000_000, env_steps=20_000)
MEDIUM = simfit.SimLimits(vector_steps=10_000_000, env_steps=20_000)  # the audit's default vectorised budget


@pytest.fixture(autouse=True)
def small_budgets(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every simulator attack in this file (the audit's too) runs within SMALL."""
    monkeypatch.setattr(simfit, "DEFAULT_LIMITS", SMALL)


def make_run(root: Path, task: str, method: str, seed: int, secrets: Secrets, *, iterations: int = 10, keyed: bool = True) -> Path:
    """A run with the offline optimizer; ``keyed=False`` makes it as runs were made before its random
    streams were keyed by its secrets: warm-up and episode seeds from the run seed alone,
    the transcripts the red team attacked (a user's old runs are such)."""
    out = root / f"{task}__{method}__{seed}"
    config = make_config(task, method, warmup=10, iterations=iterations, final_episodes=0, seed=seed)
    if keyed:
        with offline_llm():
            start(config, out, secrets=secrets)
        return out
    with Study.create(config, out, secrets=secrets) as study:
        with sqlite3.connect(out / "run.sqlite") as db:
            db.execute("DELETE FROM meta WHERE key = 'streams'")
    with offline_llm(), Study.load(out) as study:
        study.optimize()
    return out


def estimates(run: Path, task: str, limits: simfit.SimLimits = SMALL) -> dict[str, object]:
    return {e.attack: e for e in run_attacks(load_requests(run), get_task(task), (-6.0, 6.0), limits=limits)}


def err(est: float | np.ndarray, true: float | np.ndarray) -> np.ndarray:
    """Error factor minus one, as the privacy report states it."""
    return np.expm1(np.abs(np.log(np.asarray(est, dtype=np.float64) / true)))


@pytest.mark.parametrize("task", ["Pendulum-v1", "CartPole", "Acrobot"])
def test_the_vectorised_simulators_reproduce_the_real_env(task: str) -> None:
    """The numpy dynamics give the real env's returns and diagnostics, episode by episode."""
    t = get_task(task)
    fast, _ = simulator_for(t, Budget(10**8))
    exact = EnvSim(t, Budget(10**8))
    assert fast is not None and fast.kind == "vector"
    rng = np.random.default_rng(3)
    thetas = rng.uniform(-6, 6, size=(12, t.D)) * rng.uniform(0.02, 1.0, size=(12, 1))
    seeds = rng.integers(0, 2**31, size=12).tolist()
    a, b = fast.rollout(thetas, seeds), exact.rollout(thetas, seeds)
    np.testing.assert_allclose(a.returns, b.returns, rtol=1e-9, atol=1e-9)
    for k, v in b.diagnostics.items():
        if k in a.diagnostics:
            if v.dtype == object:
                assert list(a.diagnostics[k]) == list(v), k
            else:
                np.testing.assert_allclose(a.diagnostics[k].astype(float), v, atol=1e-9, err_msg=k)
    with pytest.raises(OverBudget, match="budget of 100 simulated steps"):  # a bound, not a hang
        simulator_for(t, Budget(100))[0].rollout(thetas, seeds)  # type: ignore[union-attr]


def test_the_budget_counts_simulated_steps_and_a_wall_clock_cap_is_opt_in() -> None:
    """An attack stops on its step budget, whatever time has passed; only a cap asked for
    (``--sim-seconds``) reads the clock, and none is set by default."""
    long_ago = time.monotonic() - 3600.0
    b = Budget(100, started=long_ago)
    b.charge(100)
    with pytest.raises(OverBudget, match="budget of 100 simulated steps"):
        b.charge(1)
    with pytest.raises(OverBudget, match="wall-clock cap of 1 s"):
        Budget(100, seconds=1.0, started=long_ago).charge(1)
    assert simfit.SimLimits().seconds is None and "wall clock" not in simfit.SimLimits().describe()
    assert _limits(build_parser().parse_args(["audit", "d"])).seconds is None
    capped = _limits(build_parser().parse_args(["audit", "d", "--sim-seconds", "30"]))
    assert capped.seconds == 30.0 and capped.describe().endswith("and at most 30 s of wall clock, per attack")
    for bad in ("0", "nan"):
        with pytest.raises(ConfigError, match="--sim-seconds > 0"):
            _limits(build_parser().parse_args(["audit", "d", "--sim-seconds", bad]))


def test_finding_1_the_run_seed_is_read_off_a_hardened_transcript_and_the_audit_warns(tmp_path: Path) -> None:
    """The encoded warm-up printed in the first prompt is seeding.rng(seed, WARMUP, m).uniform(-6, 6):
    a table lookup gives the run seed, hence every episode's initial state."""
    old = make_run(tmp_path / "old", "CartPole", "pp-hardened", 1234, seeded_secrets("pp-hardened", "CartPole", 0), iterations=2,
                   keyed=False)
    v = view_of(load_requests(old), get_task("CartPole"), (-6.0, 6.0))
    seed, how = find_run_seed(v)
    assert seed == 1234 and "encoded warm-up" in how
    r = audit_run(old, simulate=False)
    assert any(f.kind == "run_seed" and "read off the transcript" in f.detail for f in r.channels), r.format()
    assert r.exit_code(strict=True) == 1  # --strict fails on it
    # closed for new runs: the warm-up is keyed by the secrets, the seed is not found, the audit has nothing to warn of
    new = make_run(tmp_path / "new", "CartPole", "pp-hardened", 1234, seeded_secrets("pp-hardened", "CartPole", 0), iterations=2)
    assert find_run_seed(view_of(load_requests(new), get_task("CartPole"), (-6.0, 6.0)))[0] is None
    r = audit_run(new, simulate=False)
    assert not any(f.kind == "run_seed" for f in r.channels) and r.exit_code(strict=True) == 0, r.format()


def test_finding_2_the_exact_fit_breaks_pendulum_hardened_and_the_audit_says_exposed(tmp_path: Path,
                                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Initial states known (run seed 0): decoding the shown policies and simulating them explains
    the printed returns; the best shown policy's raw return and A come out; the audit fails."""
    monkeypatch.setattr(simfit, "DEFAULT_LIMITS", MEDIUM)
    secrets = seeded_secrets("pp-hardened", "Pendulum-v1", 0)
    run = make_run(tmp_path, "Pendulum-v1", "pp-hardened", 0, secrets, keyed=False)  # a run made before streams were keyed
    ests = estimates(run, "Pendulum-v1", MEDIUM)
    exact, exact_a = ests["sim-exact"], ests["sim-exact-a"]
    assert not exact.not_run and exact.raw, exact.detail  # type: ignore[attr-defined]
    best = max(exact.raw, key=lambda g: g.ret)  # type: ignore[attr-defined]
    true_best = max(c.ret for c in _candidates(run) if _shows(c, best))
    assert abs(best.raw_ret - true_best) / abs(true_best) < 0.01  # measured: 0.0035% (-1556.17 for -1556.22)
    assert float(np.median(err(exact_a.value, secrets.a))) < 0.10  # a_j: measured 2.6%; the prior guess: 76%
    r = audit_run(run)
    assert r.verdict().startswith("EXPOSED") and r.exit_code() == 1, r.format()
    assert any(f.kind == "sim-exact" and "raw return" in f.detail for f in r.exposed)
    assert "public dynamics: task Pendulum-v1 runs the public env Pendulum-v1" in r.format()
    assert "simulator attacks: bounded by 1e+07 simulated steps" in r.format()


def test_finding_3_the_marginal_fit_moves_c_from_the_prior_towards_the_truth(tmp_path: Path) -> None:
    """No initial states (run seeds beyond the search): the shown policies are simulated on public
    initial-state draws. With c = 8 (the prior guess 1 is off by 700%), five runs with different
    A, m, s, p: the errors of ``sim-marginal`` were measured at 373, 331, 7.6, 110 and 7506%
    (median 331%: the exponent p and c trade off), asserted below the prior's 700%;
    ``sim-marginal-lattice`` (the same hypothesis, the exact likelihood of the integer returns)
    at 131, 586, 12.1, 17.4 and 43.4% (median 43.4%), asserted below 47.9%: the median error of c
    that an outside marginal fit without the seed reached on 11 CartPole pp-hardened runs, which the
    product's own fit has to match so that the audit's number is an honest bound. (With the
    narrower encoded warm-up box of earlier versions these runs gave medians of 89% and 28.8%.)"""
    errors, lattice = [], []
    for k in range(5):
        secrets = dataclasses.replace(seeded_secrets("pp-hardened", "CartPole", k), c=8.0)
        run = make_run(tmp_path, "CartPole", "pp-hardened", 5000 + k, secrets)
        ests = estimates(run, "CartPole")
        assert "initial states unknown" in ests["sim-exact"].not_run  # type: ignore[attr-defined]
        errors.append(float(err(ests["sim-marginal"].value, 8.0)))  # type: ignore[attr-defined]
        lattice.append(float(err(ests["sim-marginal-lattice"].value, 8.0)))  # type: ignore[attr-defined]
    assert float(np.median(errors)) < 7.0, errors
    assert float(np.median(lattice)) < 0.479, lattice
    assert float(err(1.0, 8.0)) == pytest.approx(7.0)
    r = audit_run(run)  # the last run: what the audit says about it
    text = r.format()
    assert "public dynamics: task CartPole runs the public env CartPole-v1" in text and "sim-marginal: c within" in text
    assert "sim-exact (initial states unknown" in text  # listed among the attacks not run, with why


def test_finding_4_the_audit_is_not_clean_on_a_pp_run_the_fit_breaks(tmp_path: Path) -> None:
    """Pendulum-v1 under pp, run seed 1500: the old seed search stopped at a smaller seed whose
    warm-up signs matched by chance (4 parameters: 16 sign patterns), so seed-replay failed and the
    audit said CLEAN. The warm-up's scales single the seed out; A, then c and every raw value follow."""
    secrets = seeded_secrets("pp", "Pendulum-v1", 3)
    run = make_run(tmp_path, "Pendulum-v1", "pp", 1500, secrets, iterations=4, keyed=False)  # made before streams were keyed
    r = audit_run(run)
    assert r.verdict().startswith("EXPOSED"), r.format()
    kinds = {f.kind for f in r.exposed}
    assert {"seed-replay", "sim-exact"} <= kinds, kinds
    c = next(f for f in r.exposed if f.kind == "sim-exact" and f.detail.startswith("recovers c"))
    assert "to 0" in c.detail  # c within 1%
    not_run = dict(r.not_run)
    assert not_run["lattice"].startswith("fact unknown")  # Pendulum-v1 declares no privacy facts
    assert "attacks not run: " in r.format()


POINT_ROBOT = """
    import gymnasium as gym
    import numpy as np


    class PointRobot(gym.Env):
        observation_space = gym.spaces.Box(-10.0, 10.0, (2,), np.float64)
        action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float64)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.x = self.np_random.uniform(-1, 1, 2)
            self.t = 0
            return self.x.copy(), {}

        def step(self, action):
            self.x = self.x + 0.1 * np.array([float(action[0]), -self.x[1]])
            self.t += 1
            return self.x.copy(), -float(np.sum(self.x**2)), False, self.t >= 20, {}
"""


@pytest.fixture()
def point_robot(tmp_path: Path) -> Iterator[str]:
    (tmp_path / "point_robot.py").write_text(textwrap.dedent(POINT_ROBOT))
    sys.modules.pop("point_robot", None)  # another test's point_robot (examples/own_robot) may be imported already
    sys.path.insert(0, str(tmp_path))
    yield "point_robot:PointRobot"
    sys.path.remove(str(tmp_path))
    sys.modules.pop("point_robot", None)


def test_finding_5_a_module_or_class_name_of_the_users_env_in_a_prompt_is_flagged(tmp_path: Path, point_robot: str) -> None:
    """Before the prompt named tasks neutrally, it named them by the task name: here the module and
    class of the user's env. Once it names them neutrally the audit finds nothing, and a name
    planted in a recorded request is still flagged."""
    task = get_task(point_robot)
    assert not env_is_public(task)
    out = tmp_path / "run"
    with offline_llm():
        start(make_config(point_robot, "pp", warmup=3, iterations=1, final_episodes=0), out)
    r = audit_run(out)
    assert "sim-exact" in dict(r.not_run) and "private" in dict(r.not_run)["sim-exact"]
    if "point_robot" not in load_requests(out)[0].text:  # a neutral name: nothing to flag; plant one
        assert not r.identifiers, r.format()

        def plant(doc: dict[str, Any]) -> None:  # in the first recorded request
            if "messages" in doc:
                doc["messages"][0]["content"] += "\n(point_robot.PointRobot)"
            else:
                doc["prompt"] = "(point_robot.PointRobot)\n" + doc["prompt"]

        tamper_call(out, 0, request=plant)
        r = audit_run(out)
    names = {f.detail.split("'")[1] for f in r.identifiers}
    assert {"point_robot", "PointRobot"} <= names, r.format()
    assert r.verdict().startswith("IDENTIFIERS") and r.exit_code() == 1


def _candidates(run: Path) -> list:  # type: ignore[type-arg]
    from ppprops.store import open_store

    with open_store(run) as store:
        return store.candidates()


def _shows(c: object, g: object) -> bool:
    enc = np.asarray(c.params_enc)  # type: ignore[attr-defined]
    return bool(np.all(np.abs(enc - np.asarray(g.params)) <= np.asarray(g.tols) + 1e-9))  # type: ignore[attr-defined]


def _shown_raw_returns(run: Path, guesses: Any) -> np.ndarray:
    """The true raw return behind each guessed entry (``exposure.shown_candidate``: the candidate it stands for)."""
    from ppprops.privacy.exposure import shown_candidate

    cands = _candidates(run)
    return np.array([shown_candidate(g, cands).ret for g in guesses])  # type: ignore[union-attr]


def test_the_lattice_reading_names_acrobot_raw_returns_closer_than_the_marginal_fit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Acrobot pp-hardened, no initial states: the lattice reading's map, applied to each printed
    return, names its raw return far closer than the marginal fit's expected returns (s, p and c
    trade off, so the returns are pinned closer than c). On this run (seed 6000) the mean absolute
    error was 5.4 against the marginal fit's 56.9 (on ten offline runs of benchmarks/simfit_marginal.py
    --returns: 5.9 against 39.3); asserted below 12 and a quarter of the marginal fit's. The audit
    scores the reading of the best shown entry like the exact fit's."""
    secrets = seeded_secrets("pp-hardened", "Acrobot", 0)
    run = make_run(tmp_path, "Acrobot", "pp-hardened", 6000, secrets)
    ests = estimates(run, "Acrobot")
    lat, marg = ests["sim-marginal-lattice"], ests["sim-marginal"]
    assert lat.raw and len(lat.raw) == len(marg.raw)  # type: ignore[attr-defined]
    truth = _shown_raw_returns(run, lat.raw)  # type: ignore[attr-defined]
    assert all(float(g.raw_ret).is_integer() for g in lat.raw)  # type: ignore[attr-defined]  # Acrobot's returns are integers
    lattice = float(np.mean(np.abs(np.array([g.raw_ret for g in lat.raw]) - truth)))  # type: ignore[attr-defined]
    marginal = float(np.mean(np.abs(np.array([g.raw_ret for g in marg.raw]) - truth)))  # type: ignore[attr-defined]
    assert lattice < 12.0 and lattice < marginal / 4, (lattice, marginal)

    # the audit reads the lattice row's raw values: a reading that names the best shown return is an exposure
    from ppprops.privacy import exposure

    best = max(lat.raw, key=lambda g: g.ret)  # type: ignore[attr-defined]
    exact = dataclasses.replace(best, raw_ret=float(_shown_raw_returns(run, [best])[0]))
    planted = dataclasses.replace(lat, raw=tuple(exact if g is best else g for g in lat.raw))  # type: ignore[attr-defined,type-var]
    monkeypatch.setattr(exposure, "run_attacks", lambda *a, **k: [planted])
    from ppprops.client.mechanisms import PRESETS

    found = exposure.assess([], get_task("Acrobot"), (-6.0, 6.0), PRESETS["pp-hardened"], _candidates(run), secrets)
    assert [(e.attack, e.error) for e in found.exposures if e.target == "raw return"] == [("sim-marginal-lattice", 0.0)]
