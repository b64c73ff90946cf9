"""A user's env that raises, and a script without its __main__ guard.

Each is one line naming the user's exception (type, message, where in their code), exit 2, the
run marked ``failed: <reason>`` in the store and by ``show``, resumable, nothing lost.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import ppprops
from ppprops.cli import main
from ppprops.store import open_store

SRC = str(Path(__file__).resolve().parents[1] / "src")

FAULTY = textwrap.dedent('''
    import gymnasium as gym
    import numpy as np


    class Faulty(gym.Env):
        """Raises in step once it has been stepped FAIL_AT times (episodes of 10 steps)."""

        FAIL_AT = {fail_at}

        def __init__(self):
            self.observation_space = gym.spaces.Box(-10.0, 10.0, (1,), dtype=np.float64)
            self.action_space = gym.spaces.Discrete(2)
            self.calls = 0

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.x = 0.0
            return np.array([self.x]), {{}}

        def step(self, action):
            self.calls += 1
            if self.calls >= self.FAIL_AT:
                raise RuntimeError("motor driver fault")
            self.x += 0.1 if int(action) else -0.1
            return np.array([self.x]), -abs(self.x), False, self.calls % 10 == 0, {{}}
''')


def _ppprops(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "ppprops", *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.parametrize("workers", ["1", "2"])
def test_an_env_raising_mid_run_is_one_line_a_failed_status_and_resumable(tmp_path: Path, workers: str) -> None:
    (tmp_path / "faulty.py").write_text(FAULTY.format(fail_at=30))
    args = ["run", "--env", "faulty:Faulty", "--method", "random", "--warmup", "3", "--iterations", "2", "--seed", "3",
            "--final-episodes", "2", "--select-top", "0", "--out", "r", "--quiet", "--workers", workers]
    proc = _ppprops(args, tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    line = "ppprops: error: the env of task faulty:Faulty raised in step 10 (episode seed "
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(line), proc.stderr
    line_no = FAULTY.splitlines().index('            raise RuntimeError("motor driver fault")') + 1
    where = f"RuntimeError: motor driver fault (at {tmp_path / 'faulty.py'}:{line_no}, in step); the run is saved: continue with 'ppprops resume r'"
    assert proc.stderr.rstrip().endswith(where), proc.stderr
    with open_store(tmp_path / "r") as store:
        status = store.status()
        assert status.startswith("failed: the env of task faulty:Faulty raised in step 10") and "motor driver fault" in status
        assert store.candidate_count() == 2  # the two episodes before the fault are kept
    shown = json.loads(_ppprops(["show", "r", "--json"], tmp_path).stdout)
    assert shown["status"] == status and shown["counts"]["candidates"] == 2
    assert ppprops.load_run(tmp_path / "r").status == status
    (tmp_path / "faulty.py").write_text(FAULTY.format(fail_at=10**9))  # the user fixes the robot
    resumed = _ppprops(["resume", "r", "--quiet"], tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    with open_store(tmp_path / "r") as store:
        assert store.status() == "finished" and [c.index for c in store.candidates()] == [0, 1, 2, 3, 4]


def test_a_bad_env_kwarg_of_a_gymnasium_env_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--env", "Pendulum-v1", "--env-kwargs", '{"g": "heavy"}', "--method", "random", "--warmup", "2",
                 "--iterations", "1", "--out", str(tmp_path / "p"), "--quiet"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "the env of task Pendulum-v1 raised in step 1" in err and "TypeError: unsupported operand type(s) for /: 'str' and 'float'" in err
    assert "resume" not in err and not (tmp_path / "p").exists()  # refused in its first episode: nothing is kept


def test_a_script_without_its_main_guard_gets_one_clear_error_and_one_run(tmp_path: Path) -> None:
    """multiprocessing re-imports the script in each worker: the workers leave quietly (no second
    run, no traceback of theirs), and the search stops with a line that names the guard."""
    (tmp_path / "unguarded.py").write_text(
        "import ppprops\n"
        "ppprops.search('CartPole', method='random', warmup=3, iterations=2, seed=1, out='runs/x',\n"
        "               evaluation={'workers': 2, 'final_episodes': 2})\n"
    )
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "unguarded.py"], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1 and proc.stderr.count("Traceback") == 1  # the script's own uncaught error, nothing from workers
    assert 'put the code that runs the search under `if __name__ == "__main__":`' in proc.stderr.splitlines()[-1]
    assert "the worker processes of workers > 1 stopped" in proc.stderr.splitlines()[-1]
    assert not (tmp_path / "runs").exists()  # no run of the workers' own, and the refused one left nothing, not even runs/


STRING_OBSERVATION = textwrap.dedent('''
    import gymnasium as gym
    import numpy as np


    class Text(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
        action_space = gym.spaces.Discrete(2)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            return np.zeros(3, np.float32), {}

        def step(self, action):
            return "abc", 0.0, False, False, {}
''')


def test_the_console_script_says_a_malformed_value_in_one_line(tmp_path: Path) -> None:
    """The console script, as a user runs it, progress on: one line on stderr (no traceback, no
    warning, no progress bar or run directory line before it), exit 2, nothing left at --out;
    ``task check`` reports the same line on stdout and exits 1."""
    (tmp_path / "text_env.py").write_text(STRING_OBSERVATION)
    proc = _ppprops(["run", "--env", "text_env:Text", "--method", "random", "--warmup", "2", "--iterations", "1", "--out", "r"], tmp_path)
    problem = "observation 'abc' is a str, not an array of numbers (its observation space is Box(-1.0, 1.0, (3,), float32))"
    line = f"the env of task text_env:Text returned a malformed value in step 1 (episode seed SEED): {problem}"
    assert (proc.returncode, proc.stdout) == (2, "")
    assert re.fullmatch(re.escape(f"ppprops: error: {line}\n").replace("SEED", r"\d+"), proc.stderr), proc.stderr
    assert not (tmp_path / "r").exists()
    check = _ppprops(["task", "check", "--env", "text_env:Text"], tmp_path)
    assert (check.returncode, check.stderr) == (1, "")
    assert check.stdout.splitlines()[1] == "  " + line.replace("SEED", "0")


def test_a_missing_extra_leaves_no_run_directory(tmp_path: Path) -> None:
    """``--env Ant-Ultra`` on an install without MuJoCo (here its import fails): the extra's line,
    exit 2, and nothing at --out, so the same command runs once the extra is installed."""
    (tmp_path / "shim" / "mujoco").mkdir(parents=True)
    (tmp_path / "shim" / "mujoco" / "__init__.py").write_text("raise ImportError('No module named mujoco')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "shim"), SRC, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "ppprops", "run", "--env", "Ant-Ultra", "--method", "random", "--out", "runs/ant"],
                          cwd=tmp_path, capture_output=True, text=True, env=env, timeout=300)
    assert (proc.returncode, proc.stdout) == (2, "")
    assert proc.stderr == "ppprops: error: each MuJoCo task (Ant-v5, Humanoid-v5) needs the 'mujoco' extra: pip install 'ppprops[mujoco]'\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shim"]
