"""Standard RL baselines (Stable-Baselines3 defaults) stored as runs: `ppprops baseline rl`.

Every algorithm really trains, briefly, on a task whose actions it takes (CartPole for the
discrete-capable ones, Pendulum for SAC/TD3/DDPG), from the CLI; the runs are made once per module.
The ``rl`` extra is part of the test extra: without it this module fails at import, it never skips.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import sb3_contrib  # noqa: F401  (TRPO) the rl extra must be installed: fail loudly, never skip
import stable_baselines3  # noqa: F401

from ppprops import seeding
from ppprops.baselines.algorithms import ALGORITHMS
from ppprops.baselines.rl import evaluate_model, load_model, make_env
from ppprops.cli import main
from ppprops.store import open_store
from ppprops.tasks import get_task

SEED = 3
FINAL = 3
# (algorithm, task, timesteps): PPO and TRPO still collect one full 2048-step rollout.
RUNS = [
    ("ppo", "CartPole", 256),
    ("a2c", "CartPole", 256),
    ("trpo", "CartPole", 256),
    ("dqn", "CartPole", 256),
    ("sac", "Pendulum-v1", 250),
    ("td3", "Pendulum-v1", 250),
    ("ddpg", "Pendulum-v1", 250),
]


def _call(capsys, args: list[str]) -> tuple[int, str, str]:  # type: ignore[no-untyped-def]
    try:
        code = main(args)
    except SystemExit as e:  # argparse
        code = int(e.code or 0)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def _show(capsys, run_dir: Path) -> dict:  # type: ignore[no-untyped-def, type-arg]
    code, out, _ = _call(capsys, ["show", str(run_dir), "--json"])
    assert code == 0
    return dict(json.loads(out))


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One short training run per algorithm, through the CLI."""
    root = tmp_path_factory.mktemp("rl")
    dirs = {}
    scratch = root / "tempdir"  # the process's temp directory while training: nothing may be left there
    scratch.mkdir()
    saved, tempfile.tempdir = tempfile.tempdir, str(scratch)
    try:
        for algo, task, steps in RUNS:
            out = root / algo
            code = main(["baseline", "rl", "--algo", algo, "--env", task, "--timesteps", str(steps), "--seed", str(SEED),
                         "--final-episodes", str(FINAL), "--out", str(out), "--quiet"])  # fmt: skip
            assert code == 0, algo
            dirs[algo] = out
    finally:
        tempfile.tempdir = saved
    dirs["tempdir"] = scratch
    return dirs


def test_training_leaves_nothing_in_the_temp_directory(trained: dict[str, Path]) -> None:
    """SB3's default logger makes an empty SB3-<date> folder per learn(); the run's store is the log."""
    assert sorted(p.name for p in trained["tempdir"].iterdir() if p.name.startswith("SB3-")) == []  # torch may cache there


def test_the_table_covers_the_papers_seven_algorithms() -> None:
    assert {a for a, _, _ in RUNS} == set(ALGORITHMS) == {"ppo", "a2c", "sac", "td3", "ddpg", "trpo", "dqn"}


@pytest.mark.parametrize("algo,task,steps", RUNS)
def test_each_algorithm_trains_and_shows_like_a_run(capsys, trained: dict[str, Path], algo: str, task: str, steps: int) -> None:  # type: ignore[no-untyped-def]
    s = _show(capsys, trained[algo])
    assert (s["env"], s["method"], s["seed"], s["status"]) == (get_task(task).name, f"rl-{algo}", SEED, "finished")
    assert s["best"] is None and s["candidates"] == [] and s["llm_calls"] == [] and s["mechanisms"] is None
    fe = s["final_eval"]
    assert fe["episodes"] == FINAL == len(fe["returns"]) and fe["mean"] == pytest.approx(np.mean(fe["returns"]))
    t = s["training"]
    assert t["timesteps"] == steps and t["timesteps_done"] >= steps and t["wall_s"] > 0 and t["model"] == "model.zip"
    eps = t["episodes"]
    assert eps and [e["index"] for e in eps] == list(range(len(eps)))
    stamps = [e["timestep"] for e in eps]
    assert stamps == sorted(stamps) and stamps[-1] <= t["timesteps_done"]
    assert sum(e["length"] for e in eps) <= t["timesteps_done"]
    if task == "CartPole":  # +1 per step: a training return is the episode's length
        assert all(e["return"] == e["length"] for e in eps)
    else:  # Pendulum: 200-step episodes, every reward in [-16.3, 0]
        assert all(e["length"] == 200 and -16.3 * 200 <= e["return"] <= 0 for e in eps)
    # the stored config names the library defaults the model really used
    model = load_model(trained[algo])
    hp = s["config"]["hyperparameters"]
    assert hp["gamma"] == model.gamma and hp["learning_rate"] == model.learning_rate
    assert s["config"]["policy"] == "MlpPolicy" and s["config"]["versions"]["stable_baselines3"] == stable_baselines3.__version__
    code, text, _ = _call(capsys, ["show", str(trained[algo])])
    assert code == 0 and f"method rl-{algo}" in text and "fresh episodes" in text


def test_final_evaluation_uses_the_same_fresh_seeds_as_pp_props(capsys, trained: dict[str, Path], tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    search = tmp_path / "search"
    args = ["run", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "1",
            "--final-episodes", str(FINAL), "--seed", str(SEED), "--out", str(search), "--quiet"]  # fmt: skip
    code, _, _ = _call(capsys, args)
    assert code == 0
    store = open_store(search)
    pp_seeds = store.final_eval().seeds  # type: ignore[union-attr]
    store.close()
    assert list(pp_seeds) == seeding.final_eval_seeds(SEED, FINAL)
    for algo in ALGORITHMS:
        store = open_store(trained[algo])
        fe = store.final_eval()
        store.close()
        assert fe is not None and fe.seeds == pp_seeds, algo


@pytest.mark.parametrize("algo", ["ppo", "dqn", "sac"])
def test_saved_model_replays_its_final_evaluation(trained: dict[str, Path], algo: str) -> None:
    """model.zip is the evaluated agent, and the evaluation is plain deterministic play on those seeds."""
    store = open_store(trained[algo])
    fe, task = store.final_eval(), get_task(store.config()["task"])
    store.close()
    assert fe is not None
    model = load_model(trained[algo])
    assert evaluate_model(model, task, list(fe.seeds)) == fe.returns
    # an independent rollout: the raw env, the task's observation adapter, deterministic actions
    env = gym.make(task.env_id)
    returns = []
    for seed in fe.seeds:
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            action, _ = model.predict(np.asarray(task.observation(obs), dtype=np.float32), deterministic=True)
            obs, r, term, trunc, _ = env.step(int(action) if task.discrete else action)
            total, done = total + float(r), term or trunc
        returns.append(total)
    env.close()
    assert tuple(returns) == pytest.approx(fe.returns)


INAPPLICABLE = [
    ("sac", "CartPole", "discrete"),
    ("td3", "CartPole", "discrete"),
    ("ddpg", "Acrobot", "discrete"),
    ("dqn", "Pendulum-v1", "continuous"),
    ("dqn", "MountainCarContinuous-v0", "continuous"),
]


@pytest.mark.parametrize("algo,task,action_type", INAPPLICABLE)
def test_inapplicable_combination_is_one_line_and_exit_2(capsys, tmp_path: Path, algo: str, task: str, action_type: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "never"
    args = ["baseline", "rl", "--algo", algo, "--env", task, "--timesteps", "100", "--out", str(out), "--quiet"]
    code, _, err = _call(capsys, args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("ppprops: error:"), err
    assert f"{algo} (" in lines[0] and f"has {action_type} actions" in lines[0] and "'--'" in lines[0]
    assert not out.exists()


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--timesteps", "0"], "--timesteps must be >= 1"),
        (["--timesteps", "10", "--final-episodes", "-1"], "--final-episodes must be >= 0"),
        (["--timesteps", "10", "--seed", "-1"], "--seed must be in [0, 2^32)"),
        (["--timesteps", "10", "--algo", "reinforce"], "invalid choice"),
    ],
)
def test_bad_settings_are_one_line_and_exit_2(capsys, tmp_path: Path, extra: list[str], needle: str) -> None:  # type: ignore[no-untyped-def]
    args = ["baseline", "rl", "--algo", "ppo", "--env", "CartPole", "--out", str(tmp_path / "r"), "--quiet", *extra]
    code, _, err = _call(capsys, args)
    assert code == 2 and err.count("\n") == 1 and needle in err


def test_a_directory_holding_a_run_is_not_overwritten(capsys, trained: dict[str, Path]) -> None:  # type: ignore[no-untyped-def]
    before = {p.name: p.read_bytes() for p in trained["a2c"].iterdir()}
    code, _, err = _call(capsys, ["baseline", "rl", "--algo", "a2c", "--env", "CartPole", "--timesteps", "10",
                                  "--out", str(trained["a2c"]), "--quiet"])  # fmt: skip
    assert code == 2 and "already holds another run" in err
    assert {p.name: p.read_bytes() for p in trained["a2c"].iterdir()} == before


def test_resume_refuses_an_rl_run_in_one_line(capsys, trained: dict[str, Path]) -> None:  # type: ignore[no-untyped-def]
    code, _, err = _call(capsys, ["resume", str(trained["dqn"]), "--quiet"])
    assert code == 2 and err.count("\n") == 1 and "is an RL baseline run (rl-dqn)" in err


def test_the_python_api_refuses_an_rl_run_as_a_search(trained: dict[str, Path]) -> None:
    """``ppprops.load_run`` and ``ppprops.resume`` read searches; an RL run is one ConfigError, not a KeyError."""
    import ppprops
    from ppprops.errors import ConfigError

    before = {p.name: p.read_bytes() for p in trained["dqn"].iterdir()}
    with pytest.raises(ConfigError, match=r"is an RL baseline run \(rl-dqn\), not a search"):
        ppprops.load_run(trained["dqn"])
    with pytest.raises(ConfigError, match=r"is an RL baseline run \(rl-dqn\); it cannot be resumed"):
        ppprops.resume(trained["dqn"])
    assert {p.name: p.read_bytes() for p in trained["dqn"].iterdir()} == before


def test_the_agent_sees_the_ultra_observation() -> None:
    """Ant-Ultra's agent observes the 10 Ultra variables, not Ant-v5's 27-dim state."""
    pytest.importorskip("mujoco")
    task = get_task("Ant-Ultra")
    env = make_env(task)
    raw = task.make_env()
    try:
        assert env.observation_space.shape == (10,) == (task.n_s,)
        obs, _ = env.reset(seed=5)
        raw_obs, _ = raw.reset(seed=5)
        assert raw_obs.shape == (27,)
        assert obs.dtype == np.float32 and np.array_equal(obs, task.observation(raw_obs).astype(np.float32))
    finally:
        env.close()
        raw.close()


_PROBE = """
import sys
{block}
from ppprops.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as e:
    code = e.code
heavy = [m for m in ("torch", "stable_baselines3", "sb3_contrib") if m in sys.modules]
print(repr(heavy))
sys.exit(code)
"""


def _probe(args: list[str], block: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", _PROBE.format(block=block), *args], capture_output=True, text=True, timeout=120)


def test_help_and_show_do_not_import_torch(trained: dict[str, Path]) -> None:
    run = str(trained["ppo"])
    for args in (["--help"], ["baseline", "rl", "--help"], ["show", run, "--json"], ["show", run]):
        proc = _probe(args)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.strip().splitlines()[-1] == "[]", args


def test_missing_rl_extra_is_one_line_and_exit_2(tmp_path: Path) -> None:
    # an import that fails, as it does when the extra is not installed (None in sys.modules: ImportError)
    block = "sys.modules['stable_baselines3'] = None"
    args = ["baseline", "rl", "--algo", "ppo", "--env", "CartPole", "--timesteps", "10", "--out", str(tmp_path / "r")]
    proc = _probe(args, block)
    assert proc.returncode == 2
    needs = "ppprops: error: ppprops baseline rl needs the 'rl' extra: pip install 'ppprops[rl]'"
    assert proc.stderr.strip().splitlines() == [needs]
    assert not (tmp_path / "r").exists()
