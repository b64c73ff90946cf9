"""The user's identifiers stay home: under every preset that encodes
parameters a prompt names a user's task by a neutral name, or by the display name its task file
gives for the provider; never by its module, class, file or directory."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.store import open_store

from support import offline_llm

ENV = '''
import gymnasium as gym
import numpy as np


class SecretArmController(gym.Env):
    def __init__(self):
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (2,), dtype=np.float64)
        self.action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.t = float(self.np_random.uniform(-1, 1)), 0
        return np.array([self.x, 0.0]), {}

    def step(self, action):
        self.t += 1
        self.x += 0.1 if int(action) else -0.1
        return np.array([self.x, 0.0]), -abs(self.x), False, self.t >= 20, {}
'''


def _prompts(run_dir: Path) -> str:
    with open_store(run_dir) as store:
        return "\n".join(str(c["request"]) for c in store.llm_calls())


@pytest.mark.parametrize("method,form", [("pp", "document"), ("pp", "chat"), ("pp-hardened", "document"), ("pe", "chat")])
def test_a_user_task_is_named_neutrally(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, method: str, form: str) -> None:
    (tmp_path / "acme_robotics_private.py").write_text(ENV)
    monkeypatch.chdir(tmp_path)
    with offline_llm():
        assert main(["run", "--env", "acme_robotics_private:SecretArmController", "--method", method, "--prompt-form", form,
                     "--warmup", "3", "--iterations", "2", "--final-episodes", "0", "--out", "r", "--quiet"]) == 0
    sent = _prompts(tmp_path / "r")
    assert sent and "acme_robotics_private" not in sent and "SecretArmController" not in sent and str(tmp_path) not in sent
    if form == "document":
        assert json.loads(sent.splitlines()[0])["prompt"].startswith("# Task: linear policy search.")


def test_a_display_name_from_the_task_file_is_shown(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "acme_robotics_private.py").write_text(ENV)
    (tmp_path / "arm.toml").write_text('name = "AcmeArm"\nenv = "acme_robotics_private:SecretArmController"\n'
                                       'prompt_name = "a planar arm"\nmax_episode_steps = 20\n')
    monkeypatch.chdir(tmp_path)
    with offline_llm():
        assert main(["run", "--task-file", "arm.toml", "--method", "pp", "--prompt-form", "document", "--warmup", "3",
                     "--iterations", "1", "--final-episodes", "0", "--out", "r", "--quiet"]) == 0
    sent = _prompts(tmp_path / "r")
    assert json.loads(sent.splitlines()[0])["prompt"].startswith("# a planar arm: linear policy search.")
    assert "AcmeArm" not in sent and "acme_robotics_private" not in sent


def test_the_paper_tasks_keep_their_public_names(tmp_path: Path) -> None:
    with offline_llm():
        assert main(["run", "--env", "CartPole", "--method", "pp", "--prompt-form", "document", "--warmup", "3",
                     "--iterations", "1", "--final-episodes", "0", "--out", str(tmp_path / "r"), "--quiet"]) == 0
    assert json.loads(_prompts(tmp_path / "r").splitlines()[0])["prompt"].startswith("# CartPole: linear policy search.")
