"""The recipes of docs/architecture.md, followed as written: a toy method, a toy task, a toy attack.

Each test also checks that the doc still shows the code it runs (so the page and the test cannot
drift apart), then asserts what the recipe promises: the method runs through the loop, the task
file is searched, the attack appears in the privacy report with its error scored.
"""

from __future__ import annotations

import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import ppprops
from ppprops.client.secrets import Secrets
from ppprops.errors import ConfigError
from ppprops.loop import Phase
from ppprops.methods import METHODS, Method, MethodKind, register_method
from ppprops.privacy import attacks
from ppprops.privacy.attacks import register_attack
from ppprops.privacy.report import privacy_report
from ppprops.privacy.simulate import offline_llm
from ppprops.privacy.view import Estimate, View
from ppprops.proposers.base import Proposal, clip_to_box
from ppprops.runner import start
from ppprops.values import Candidate

from support import make_config

DOC = (Path(__file__).resolve().parents[1] / "docs" / "architecture.md").read_text(encoding="utf-8")


def _in_doc(*snippets: str) -> None:
    for s in snippets:
        assert s in DOC, f"docs/architecture.md no longer shows: {s}"


# -- add a method ----------------------------------------------------------------------------
class Shrink:
    """Black box: the best policy so far, shrunk towards 0 by half each ask."""

    def __init__(self, D: int, box: tuple[float, float]) -> None:
        self.D, self.box, self.best = D, box, None

    def ask(self, iteration: int) -> Proposal:
        base = np.zeros(self.D) if self.best is None else self.best.params
        theta, clipped = clip_to_box(0.5 * base, self.box)
        return Proposal(theta, "shrink", clipped)

    def tell(self, candidate: Candidate) -> None:
        if self.best is None or candidate.ret > self.best.ret:
            self.best = candidate


@pytest.fixture
def shrink_method() -> Iterator[Method]:
    m = register_method(Method("shrink", MethodKind.BLACK_BOX, "shrink the best policy towards 0",
                               iteration_unit="samples",
                               phase=lambda s: Phase("shrink", Shrink(s.task.D, s.config.box), s.config.iterations)))  # fmt: skip
    yield m
    del METHODS["shrink"]


def test_recipe_add_a_method(shrink_method: Method, tmp_path: Path) -> None:
    _in_doc("class Shrink:", "register_method(Method(\"shrink\", MethodKind.BLACK_BOX", 'ppprops.search(task, method="shrink")')
    result = ppprops.search("CartPole", method="shrink", warmup=4, iterations=3, final_episodes=0, seed=1, out=tmp_path / "r")
    assert result.status == "finished"
    sources = [c.source for c in result.history]
    assert sources == ["warmup"] * 4 + ["shrink"] * 3
    # each shrink candidate is half the best candidate before it (clipped to the box)
    for i in range(4, 7):
        before = result.history[:i]
        best = max(before, key=lambda c: c.ret)  # ties: the first, as Shrink.tell keeps it
        np.testing.assert_allclose(result.history[i].params, np.clip(0.5 * best.params, -6.0, 6.0))
    with pytest.raises(ConfigError, match="already registered"):
        register_method(shrink_method)


# -- add a task ------------------------------------------------------------------------------
DRIFT_ENV = '''
import gymnasium as gym
import numpy as np


class Drift(gym.Env):
    """A point on a line moves 0.1 left (action 0) or right (1); reward -|x| per step."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-10.0, 10.0, (1,), dtype=np.float64)
        self.action_space = gym.spaces.Discrete(2)
        self.x = 0.0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = float(self.np_random.uniform(-1.0, 1.0))
        return np.array([self.x]), {}

    def step(self, action):
        self.x += 0.1 if int(action) == 1 else -0.1
        return np.array([self.x]), -abs(self.x), False, False, {"distance": abs(self.x)}
'''


def test_recipe_add_a_task(tmp_path: Path) -> None:
    start_, end = DOC.index("# drift.toml, next to drift_env.py"), DOC.index("```", DOC.index("# drift.toml"))
    toml = DOC[start_:end]  # the task file exactly as the doc shows it
    _in_doc('ppprops.search("drift.toml", method="random")')
    (tmp_path / "drift_env.py").write_text(textwrap.dedent(DRIFT_ENV))
    (tmp_path / "drift.toml").write_text(toml)
    result = ppprops.search(tmp_path / "drift.toml", method="random", warmup=3, iterations=4, final_episodes=2, seed=0,
                            out=tmp_path / "run")  # fmt: skip
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
def return_per_step(v: View) -> Estimate:
    """c = printed return / episode_length (CartPole pays 1 per step)."""
    ratios = [e.ret / float(e.diagnostics["episode_length"]) for e in v.entries
              if e.diagnostics.get("episode_length", "").replace(".", "").isdigit()]  # fmt: skip
    if not ratios:
        return Estimate("return-per-step", "c", None, "no episode_length shown")
    return Estimate("return-per-step", "c", float(np.median(ratios)), f"{len(ratios)} entries")


@pytest.fixture
def toy_attack() -> Iterator[None]:
    register_attack("return-per-step", "c", return_per_step)
    yield
    del attacks.ATTACKS["return-per-step"], attacks.TARGET["return-per-step"]


def test_recipe_add_a_privacy_attack(toy_attack: None, tmp_path: Path) -> None:
    _in_doc("def return_per_step(v):", 'register_attack("return-per-step", "c", return_per_step)')
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
    with pytest.raises(ValueError, match="already registered"):
        register_attack("return-per-step", "c", return_per_step)
    with pytest.raises(ValueError, match="'c' or 'a'"):
        register_attack("other", "x", return_per_step)
