"""A robot outside Python drives a study from the shell.

``ppprops study create`` / ``ask`` / ``tell`` / ``study finalize`` in separate processes give the
same trials, store and best policy as ``ppprops.search``'s loop with the same seeds, secrets and a
fixed LLM (the fault server's synthetic answers, the same in arrival order for the same seed), and
examples/robot_outside/drive.sh (an awk "robot" that never imports ppprops) runs to the end and
audits clean.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from ppprops.client.secrets import Secrets
from ppprops.config import RunConfig
from ppprops.evaluation import make_policy, run_episode
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.tasks import get_task
from ppprops.testing.fault_server import FaultConfig, FaultServer

ROOT = Path(__file__).resolve().parents[1]
SRC = str(ROOT / "src")
EXAMPLE = ROOT / "examples" / "robot_outside"
# tests/fixed_secrets: a child process with this folder first on PYTHONPATH and the variable set draws
# its secrets from default_rng(seed) and takes a fixed run id
FIXED_SECRETS = str(ROOT / "tests" / "fixed_secrets")
SECRETS_SEED = "PPPROPS_TEST_SECRETS_SEED"


def _ppprops(args: list[str], cwd: Path, stdin: str | None = None, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    env = env if env is not None else {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "ppprops", *args], cwd=cwd, input=stdin, capture_output=True, text=True, env=env,
                          timeout=300)  # fmt: skip


def _episodes(trial: dict[str, Any]) -> dict[str, Any]:
    """The feedback of a trial as a user's own CartPole runner reports it (one entry per episode)."""
    import numpy as np

    task = get_task("CartPole")
    env = task.make_env()
    eps = [run_episode(task, env, make_policy(task, np.asarray(trial["theta"]), env), s) for s in trial["seeds"]]
    env.close()
    return {"returns": [e.ret for e in eps], "components": [e.components for e in eps], "diagnostics": [e.diagnostics for e in eps]}


def _record(run_dir: Path) -> dict[str, Any]:
    with open_store(run_dir) as store:
        cands = store.candidates()
        calls = store.llm_calls()
        fe = store.final_eval()
    return {
        "candidates": [(c.index, c.source, c.params.tolist(), c.params_enc.tolist(), c.ret, c.feedback_enc.ret, c.seeds) for c in cands],
        "requests": [json.loads(c["request"]) for c in calls],
        "final": None if fe is None else (fe.candidate_index, fe.returns, fe.seeds),
        "policy": json.loads((run_dir / "best_policy.json").read_text())["theta"],
    }


@pytest.mark.parametrize("method", ["pp", "pp-hardened"])
def test_the_shell_loop_gives_the_same_run_as_search(tmp_path: Path, method: str) -> None:
    flags = ["--env", "CartPole", "--method", method, "--warmup", "4", "--iterations", "4", "--seed", "7", "--final-episodes", "3", "--select-top", "0",
             "--episodes", "2", "--model", "m", "--retries", "0"]  # fmt: skip
    with FaultServer(FaultConfig(fault_rate=0.0, seed=5)) as server:
        # fixed secrets and run id for the verdict below (tests/fixed_secrets): the secrets are drawn here, at create
        made = _ppprops(["study", "create", *flags, "--base-url", server.base_url, "--out", "shell"], tmp_path, env=_fixed_secrets_env(11))
        assert made.returncode == 0 and made.stdout.strip() == "study directory: shell", made.stderr
        transcript = []
        while True:
            asked = _ppprops(["ask", "shell"], tmp_path)
            if asked.returncode == 3:
                assert "nothing more to ask" in asked.stderr
                break
            assert asked.returncode == 0, asked.stderr
            trial = json.loads(asked.stdout)
            assert len(trial["W"]) == 4 and len(trial["W"][0]) == 2 and len(trial["b"]) == 2 and len(trial["seeds"]) == 2
            told = _ppprops(["tell", "shell", str(trial["trial"]), "--stdin"], tmp_path, stdin=json.dumps(_episodes(trial)))
            assert told.returncode == 0, told.stderr
            transcript.append(told.stdout.strip())
        assert len(transcript) == 8 and transcript[0].startswith("trial 0: return ")
        done = _ppprops(["study", "finalize", "shell"], tmp_path)
        assert done.returncode == 0, done.stderr
    with open_store(tmp_path / "shell") as store:
        config = RunConfig.from_json(store.config())
        run_id = store.run_id()
    assert run_id.endswith("__20261204-000000-0000")  # the seam's: fixed secrets
    secrets = Secrets.load(tmp_path / "shell" / "secrets.key", run_id=run_id, D=10)
    with FaultServer(FaultConfig(fault_rate=0.0, seed=5)) as server:  # the same answers, in the same order
        from dataclasses import replace

        start(replace(config, llm=replace(config.llm, base_url=server.base_url)), tmp_path / "loop", secrets=secrets)
    shell, loop = _record(tmp_path / "shell"), _record(tmp_path / "loop")
    assert shell == loop
    assert [c[1] for c in shell["candidates"]] == ["warmup"] * 4 + ["llm"] * 4
    # the transcript's checks and attacks: the simulator fits on a public env's few shown entries are
    # tests/test_simulator_attacks.py's matter (on fresh secrets they read the best shown raw return, most
    # often when it is the cap of 500, or c within 1% in a few runs of a hundred: EXPOSED)
    audit = _ppprops(["audit", "shell", "--no-simulate"], tmp_path)
    if method == "pp-hardened":
        assert audit.returncode == 0 and "verdict: CLEAN" in audit.stdout, audit.stdout
    else:
        assert "LEAK" not in audit.stdout and "UNVERIFIED" not in audit.stdout, audit.stdout


def test_bad_tells_are_one_line_and_store_nothing(tmp_path: Path) -> None:
    assert _ppprops(["study", "create", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "1",
                     "--out", "s"], tmp_path).returncode == 0  # fmt: skip
    trial = json.loads(_ppprops(["ask", "s"], tmp_path).stdout)
    bad = [
        (["tell", "s", "0"], "tell needs --return R (or --stdin with a JSON object)"),
        (["tell", "s", "0", "--return", "nan"], "argument --return: expected a finite number, got 'nan'"),
        (["tell", "s", "0", "--return", "x"], "argument --return: expected a number, got 'x'"),
        (["tell", "s", "3", "--return", "1"], "trial 3 has not been asked yet: ask hands out the next trial (1)"),
        (["tell", "s", "0", "--return", "1", "--diagnostic", "speed=3"], "unknown diagnostic 'speed'"),
        (["tell", "s", "0", "--return", "1", "--diagnostic", "episode_length=abc"], "diagnostic 'episode_length' = 'abc' is not a number of steps"),
        (["tell", "s", "0", "--return", "1", "--component", "x"], "--component must be NAME=VALUE, got 'x'"),
        (["tell", "s", "0", "--return", "1", "--component", "x=fast"], "--component x='fast': expected a number"),
        (["tell", "s", "0", "--stdin"], "stdin is not a JSON object"),
        (["tell", "nowhere", "0", "--return", "1"], "nowhere is not a ppprops run directory"),
        (["tell", "s", "-1", "--return", "1"], "trial -1 does not exist: trials are numbered from 0"),
    ]
    for args, message in bad:
        proc = _ppprops(args, tmp_path, stdin="")
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and message in proc.stderr, (args, proc.stderr)
    with open_store(tmp_path / "s") as store:
        assert store.candidate_count() == 0 and store.pending_trial() is not None
    assert json.loads(_ppprops(["ask", "s"], tmp_path).stdout) == trial  # still the same trial
    ok = _ppprops(["tell", "s", "0", "--return", "12", "--diagnostic", "episode_length=12", "--diagnostic", "termination=pole_fell"],
                  tmp_path)  # fmt: skip
    assert ok.returncode == 0 and ok.stdout.startswith("trial 0: return 12; best 12 (trial 0); 1 of 8 told")  # 2 + 1 + 5 re-evaluations
    again = _ppprops(["tell", "s", "0", "--return", "12"], tmp_path)
    assert again.returncode == 2 and "trial 0 was already told" in again.stderr


def test_episodes_told_must_match_the_trial_and_an_early_finalize_says_so(tmp_path: Path) -> None:
    """A trial asked for 2 episodes takes 2 returns, not 1; a study finalized before its budget says
    so once, and ask afterwards says it is finalized (not "all 1 of 4 told; finalize it")."""
    assert _ppprops(["study", "create", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "2",
                     "--episodes", "2", "--select-top", "0", "--final-episodes", "0", "--out", "s"], tmp_path).returncode == 0  # fmt: skip
    trial = json.loads(_ppprops(["ask", "s"], tmp_path).stdout)
    assert len(trial["seeds"]) == 2
    one = _ppprops(["tell", "s", "0", "--return", "12"], tmp_path)
    assert one.returncode == 2 and one.stderr.count("\n") == 1
    assert "trial 0 asked for 2 episodes (its seeds) and 1 return(s) were told" in one.stderr
    with open_store(tmp_path / "s") as store:
        assert store.candidate_count() == 0
    fb = json.dumps({"returns": [12, 14], "diagnostics": [{"episode_length": 12}, {"episode_length": 14}]})
    both = _ppprops(["tell", "s", "0", "--stdin"], tmp_path, stdin=fb)
    assert both.returncode == 0 and both.stdout.startswith("trial 0: return 13; best 13 (trial 0); 1 of 4 told"), both.stderr
    early = _ppprops(["study", "finalize", "s"], tmp_path)
    assert early.returncode == 0 and "note: study finalized after 1 of its 4 planned trials" in early.stderr
    after = _ppprops(["ask", "s"], tmp_path)
    assert after.returncode == 3 and after.stderr.strip() == "ppprops: study s is finalized (1 of 4 trials told): nothing more to ask"


def test_a_task_without_env_is_driven_by_ask_tell_and_refused_by_run(tmp_path: Path) -> None:
    shutil.copy(EXAMPLE / "robot.toml", tmp_path / "robot.toml")
    run = _ppprops(["run", "--task-file", "robot.toml", "--method", "random", "--out", "r"], tmp_path)
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "has no env" in run.stderr and "ppprops ask" in run.stderr
    assert not (tmp_path / "r").exists()  # refused before anything was made
    assert _ppprops(["study", "create", "--task-file", "robot.toml", "--method", "random", "--warmup", "2", "--iterations", "1",
                     "--out", "s"], tmp_path).returncode == 0  # fmt: skip
    for _ in range(3):
        trial = json.loads(_ppprops(["ask", "s"], tmp_path).stdout)
        assert len(trial["theta"]) == 14
        comps = ["--component", "reward_distance=-50", "--component", "reward_effort=-1"]
        told = _ppprops(["tell", "s", str(trial["trial"]), "--return", str(-51 - trial["trial"]), *comps,
                         "--diagnostic", "final_distance=0.1", "--diagnostic", "reached=0"], tmp_path)  # fmt: skip
        assert told.returncode == 0, told.stderr
    missing = _ppprops(["ask", "s"], tmp_path)
    assert missing.returncode == 3
    done = _ppprops(["study", "finalize", "s", "--return", "-40", "--return", "-42"], tmp_path)
    assert done.returncode == 0, done.stderr
    doc = json.loads((tmp_path / "s" / "best_policy.json").read_text())
    assert doc["env"] is None and doc["search"]["candidate"] == 0 and doc["final_eval"]["mean"] == -41.0
    evaluated = _ppprops(["policy", "eval", "s"], tmp_path)
    assert evaluated.returncode == 2 and "no env" in evaluated.stderr


def _fixed_secrets_env(seed: int) -> dict[str, str]:
    """The environment of a child process that draws fixed secrets and a fixed run id (tests/fixed_secrets)."""
    path = os.pathsep.join(p for p in [FIXED_SECRETS, SRC, os.environ.get("PYTHONPATH")] if p)
    return {**os.environ, "PYTHONPATH": path, SECRETS_SEED: str(seed)}


def test_the_fixed_secrets_seam_reaches_the_child_process(tmp_path: Path) -> None:
    flags = ["study", "create", "--env", "CartPole", "--method", "pp-hardened", "--warmup", "2", "--iterations", "1"]  # no --seed
    keys = []
    for name, env in [("a", _fixed_secrets_env(7)), ("b", _fixed_secrets_env(7)), ("c", {**_fixed_secrets_env(7), SECRETS_SEED: ""})]:
        made = subprocess.run([sys.executable, "-m", "ppprops", *flags, "--out", name], cwd=tmp_path, capture_output=True, text=True,
                              env=env, timeout=300)  # fmt: skip
        assert made.returncode == 0, made.stderr
        keys.append((tmp_path / name / "secrets.key").read_bytes())
    assert keys[0] == keys[1]  # the same secrets, run id and run seed (the id holds it)
    task, method, seed, tail = json.loads(keys[0])["run_id"].split("__")
    assert (task, method, tail) == ("CartPole", "pp-hardened", "20261204-000000-0000") and int(seed) >= 1 << 16
    assert keys[2] != keys[0]  # the variable unset: fresh ones
    bad = subprocess.run([sys.executable, "-c", "pass"], env={**_fixed_secrets_env(7), SECRETS_SEED: "x"}, capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode != 0 and "cannot fix the secrets" in bad.stderr  # never fresh secrets by mistake


@pytest.mark.skipif(shutil.which("awk") is None or shutil.which("bash") is None, reason="the example needs bash and awk")
def test_the_robot_outside_example_runs_to_the_end(tmp_path: Path) -> None:
    # fixed secrets and run id (tests/fixed_secrets) for the verdict: on fresh ones an attack reads a value by chance now and then
    env = {**_fixed_secrets_env(3), "PPPROPS_METHOD": "pp-hardened", "PPPROPS_WARMUP": "4", "PPPROPS_ITERATIONS": "3"}
    bindir = tmp_path / "bin"  # `ppprops` as the installed console script would be, for this interpreter
    bindir.mkdir()
    (bindir / "ppprops").write_text(f"#!/bin/sh\nexec {sys.executable} -m ppprops \"$@\"\n")
    (bindir / "ppprops").chmod(0o755)
    env["PATH"] = f"{bindir}{os.pathsep}{env['PATH']}"
    with FaultServer(FaultConfig(fault_rate=0.0, seed=1)) as server:
        proc = subprocess.run(["bash", str(EXAMPLE / "drive.sh"), "study", "--base-url", server.base_url, "--model", "m"],
                              cwd=tmp_path, capture_output=True, text=True, env=env, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    with open_store(tmp_path / "study") as store:
        assert store.status() == "finished" and store.candidate_count() == 7
        assert [c.source for c in store.candidates()].count("llm") == 3 and len(store.llm_calls()) == 3
    assert json.loads((tmp_path / "study" / "best_policy.json").read_text())["W"]
    assert json.loads((tmp_path / "study" / "secrets.key").read_text())["run_id"].endswith("__20261204-000000-0000")  # the seam's
    audit = _ppprops(["audit", "study"], tmp_path)
    assert audit.returncode == 0 and "verdict: CLEAN" in audit.stdout, audit.stdout
