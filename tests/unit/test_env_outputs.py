"""An env that returns malformed values (it does not raise): each is one line naming the env, the
call, the episode seed and the value; exit 2; the run stored as ``failed: <that line>`` and
resumable once the env is fixed; ``ppprops task check`` reports the same line, with no traceback.
Through ``ppprops run``, ``ppprops.search``, a study's own env loop (``Study.optimize``) and
``ppprops task check``; and the checks themselves (``ppprops.tasks.outputs``), value by value.
"""

from __future__ import annotations

import json
import re
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import ppprops
from ppprops.cli import main
from ppprops.evaluation import MalformedEnvError
from ppprops.store import open_store
from ppprops.tasks.outputs import OutputCheck, SpaceCheck, flag_problem, info_problem, reward_problem

BAD_ENV = textwrap.dedent('''
    import gymnasium as gym
    import numpy as np

    BROKEN = True  # the tests "fix the env" by setting it to False


    class Good(gym.Env):
        """Three observed values, two actions, episodes of 5 steps; each subclass breaks one value while BROKEN."""

        observation_space = gym.spaces.Box(-10.0, 10.0, (3,), dtype=np.float64)
        action_space = gym.spaces.Discrete(2)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.t = 0
            return (self.first() if BROKEN else np.zeros(3)), {}

        def step(self, action):
            self.t += 1
            obs = self.observe() if BROKEN else np.full(3, 0.1 * self.t)
            return obs, (self.reward() if BROKEN else 1.0), False, self.t >= 5, {}

        def first(self):
            return np.zeros(3)

        def observe(self):
            return np.full(3, 0.1 * self.t)

        def reward(self):
            return 1.0


    class FiveValues(Good):
        def first(self):
            return np.zeros(5)


    class NoneReward(Good):
        def reward(self):
            return None


    class ListReward(Good):
        def reward(self):
            return [1.0, 2.0]


    class StringObservation(Good):
        def observe(self):
            return "abc"


    class ObjectObservation(Good):
        def observe(self):
            return np.array([0.1, None, 0.3], dtype=object)


    class NaNReward(Good):
        def reward(self):
            return float("nan") if self.t == 3 else 1.0


    class InfObservation(Good):
        def first(self):
            return np.array([0.0, np.inf, 0.0])
''')

SPACE = "Box(-10.0, 10.0, (3,), float64)"
# (class, the call that returns it, what is wrong): the five malformed values of the front-door report
CASES = [
    ("FiveValues", "reset", f"observation has shape (5,), but its observation space {SPACE} has shape (3,)"),
    ("NoneReward", "step 1", "reward None is not a number"),
    ("ListReward", "step 1", "reward [1.0, 2.0] is a list of 2, not a number"),
    ("StringObservation", "step 1", f"observation 'abc' is a str, not an array of numbers (its observation space is {SPACE})"),
    ("ObjectObservation", "step 1", f"observation [0.1, None, 0.3] has dtype object, not numbers (its observation space is {SPACE})"),
]
IDS = [c[0] for c in CASES]


@pytest.fixture
def bad_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    (tmp_path / "bad_env.py").write_text(BAD_ENV)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("bad_env", None)


def _line(cls: str, call: str, seed: int, problem: str) -> str:
    return f"the env of task bad_env:{cls} returned a malformed value in {call} (episode seed {seed}): {problem}"


RUN = ["--method", "random", "--warmup", "2", "--iterations", "1", "--final-episodes", "1", "--select-top", "0", "--quiet"]


def _line_pattern(cls: str, call: str, problem: str) -> str:
    """``_line`` with any episode seed (a refused run keeps no store to read the seed from)."""
    return re.escape(_line(cls, call, 0, problem)).replace(r"episode\ seed\ 0", r"episode\ seed\ \d+")


@pytest.mark.parametrize(("cls", "call", "problem"), CASES, ids=IDS)
def test_ppprops_run_refused_in_its_first_episode_is_one_line_and_leaves_nothing(bad_env: Path, cls: str, call: str, problem: str,
                                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    before = sorted(p.name for p in bad_env.iterdir())
    code = main(["run", "--env", f"bad_env:{cls}", "--out", "deep/a/r", *RUN[:-1]])  # not --quiet: no progress before the line either
    out, err = capsys.readouterr()
    assert (code, out) == (2, "")
    assert re.fullmatch(f"ppprops: error: {_line_pattern(cls, call, problem)}\n", err), err
    assert sorted(p.name for p in bad_env.iterdir()) == before  # no run directory, nor the folders made above it
    sys.modules["bad_env"].BROKEN = False  # the user fixes the env: the same command, the same --out, runs
    assert main(["run", "--env", f"bad_env:{cls}", "--out", "deep/a/r", *RUN, "--audit", "off"]) == 0
    capsys.readouterr()
    with open_store(bad_env / "deep" / "a" / "r") as store:
        assert store.status() == "finished" and [c.index for c in store.candidates()] == [0, 1, 2]


@pytest.mark.parametrize(("cls", "call", "problem"), CASES, ids=IDS)
def test_search_and_a_studys_env_loop_raise_the_same_line(bad_env: Path, cls: str, call: str, problem: str) -> None:
    with pytest.raises(MalformedEnvError) as raised:
        ppprops.search(f"bad_env:{cls}", method="random", warmup=2, iterations=1, seed=1, out="s",
                       evaluation={"final_episodes": 1, "select_top": 0})
    assert re.fullmatch(_line_pattern(cls, call, problem), str(raised.value)), str(raised.value)
    assert not (bad_env / "s").exists()  # search() made the run: refused in its first episode, it leaves nothing
    with ppprops.create_study(f"bad_env:{cls}", method="random", warmup=2, iterations=1, seed=1, storage="st",
                              evaluation={"final_episodes": 1, "select_top": 0}) as study:
        with pytest.raises(MalformedEnvError) as raised:
            study.optimize()
        line = _line(cls, call, study.pending.seeds[0], problem)  # type: ignore[union-attr]
        assert str(raised.value) == f"{line}; the run is saved: continue with 'ppprops resume st'"
        assert study.status == (ppprops.study.RunStatus.FAILED, line)


@pytest.mark.parametrize(("cls", "call", "problem"), CASES, ids=IDS)
def test_task_check_reports_the_same_line_and_exits_1(bad_env: Path, cls: str, call: str, problem: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["task", "check", "--env", f"bad_env:{cls}"]) == 1
    out, err = capsys.readouterr()
    assert err == ""
    assert out == (f"task bad_env:{cls}: one zero-policy episode (seed 0): 0 steps, the env returned a malformed value; 1 problem:\n"
                   f"  {_line(cls, call, 0, problem)}\n")
    assert main(["task", "check", "--env", f"bad_env:{cls}", "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert (doc["ok"], doc["malformed"], doc["raised"], doc["problems"]) == (False, True, False, [_line(cls, call, 0, problem)])


@pytest.mark.parametrize(("cls", "call", "what", "steps"), [
    ("NaNReward", "step 3", "reward nan", 3),
    ("InfObservation", "reset", "observation [ 0. inf  0.]", 0),
])
def test_task_check_reports_a_non_finite_value_where_a_run_would_end_the_episode(bad_env: Path, cls: str, call: str, what: str,
                                                                                steps: int, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["task", "check", "--env", f"bad_env:{cls}", "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert (doc["ok"], doc["steps"], doc["problems"]) == (False, steps, [
        f"bad_env:{cls}: the env's {call} (episode seed 0) returned a non-finite {what}; a run ends each such episode "
        "there and keeps it out of the prompt"])


def test_a_good_env_passes_every_check(bad_env: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["task", "check", "--env", "bad_env:Good"]) == 0
    assert capsys.readouterr().out == "task bad_env:Good: one zero-policy episode (seed 0): 5 steps, ended; no problem\n"


# -- the checks, value by value ----------------------------------------------------------------------------------
BOX = gym.spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)


def test_an_observation_of_a_box_may_be_any_numeric_array_of_its_shape_out_of_bounds_or_not_finite_too() -> None:
    check = SpaceCheck(BOX)
    for fine in (np.zeros(3, np.float32), np.zeros(3), np.arange(3), np.array([5.0, np.nan, -np.inf]), [0.1, 0.2, 0.3],
                 np.zeros(3, bool)):
        assert check.problem(fine) is None, fine
    space = "Box(-1.0, 1.0, (3,), float32)"
    assert check.problem(np.zeros((3, 1))) == f"observation has shape (3, 1), but its observation space {space} has shape (3,)"
    assert check.problem(None) == f"observation None is not an array of numbers (its observation space is {space})"
    assert check.problem([1.0, [2.0, 3.0]]) == (f"observation [1.0, [2.0, 3.0]] is a list of 2, not an array of numbers "
                                                f"(its observation space is {space})")
    assert check.problem(np.array(["a", "b", "c"])) == (f"observation ['a', 'b', 'c'] has dtype <U1, not numbers "
                                                        f"(its observation space is {space})")
    assert check.problem(np.zeros(3, complex)) == (f"observation [0.+0.j, 0.+0.j, 0.+0.j] has dtype complex128, not numbers "
                                                   f"(its observation space is {space})")


def test_a_discrete_observation_is_an_integer_in_the_spaces_range() -> None:
    check = SpaceCheck(gym.spaces.Discrete(4, start=1))
    for fine in (1, np.int64(4), np.array(2)):
        assert check.problem(fine) is None, fine
    assert check.problem(0) == "observation 0 is outside its observation space Discrete(4, start=1) (integers 1 to 4)"
    assert check.problem(5) == "observation 5 is outside its observation space Discrete(4, start=1) (integers 1 to 4)"
    assert check.problem(2.0) == "observation 2.0 is a float, not an integer (its observation space is Discrete(4, start=1))"
    assert check.problem(True) == "observation True is a bool, not an integer (its observation space is Discrete(4, start=1))"


def test_a_dict_observation_has_the_entries_the_policy_sees_each_fitting_its_space() -> None:
    space = gym.spaces.Dict({"a": gym.spaces.Box(-1, 1, (2,)), "b": gym.spaces.Box(-1, 1, (1,)), "c": gym.spaces.Discrete(2)})
    check = SpaceCheck(space, ("a", "b"))
    assert check.problem({"a": np.zeros(2), "b": np.zeros(1), "c": "not seen"}) is None
    assert check.problem({"a": np.zeros(2)}) == "observation has no entry 'b' (its entries: a)"
    assert check.problem({"a": np.zeros(3), "b": np.zeros(1)}) == (
        "observation entry 'a' has shape (3,), but its observation space Box(-1.0, 1.0, (2,), float32) has shape (2,)")
    assert check.problem(np.zeros(3)).startswith(  # type: ignore[union-attr]
        "observation [0., 0., 0.] is an array of shape (3,) and dtype float64, not a dict (its observation space is Dict(")


def test_a_reward_is_a_real_number_of_any_value() -> None:
    for fine in (1, 1.5, np.float32(2.0), np.int64(3), np.float64("nan"), float("inf"), np.array(0.5), True, np.bool_(False)):
        assert reward_problem(fine) is None, fine
    assert reward_problem(None) == "reward None is not a number"
    assert reward_problem("1.0") == "reward '1.0' is a str, not a number"
    assert reward_problem((1.0,)) == "reward (1.0,) is a tuple of 1, not a number"
    assert reward_problem(np.array([1.0])) == "reward [1.] is an array of shape (1,) and dtype float64, not a number"
    assert reward_problem(1 + 2j) == "reward (1+2j) is a complex number, not a real one"


def test_the_flags_are_booleans_and_info_a_dict() -> None:
    for fine in (True, False, np.bool_(True), 0, 1, np.int8(1), np.array(False)):
        assert flag_problem("terminated", fine) is None, fine
    assert flag_problem("terminated", None) == "terminated None is not a bool"
    assert flag_problem("truncated", "False") == "truncated 'False' is a str, not a bool"
    assert flag_problem("truncated", 2) == "truncated 2 is an int, not a bool"
    assert info_problem({}) is None
    assert info_problem([]) == "info [] is a list of 0, not a dict"


class _Env:
    observation_space = BOX


def test_reset_and_step_return_tuples_of_two_and_five() -> None:
    check = OutputCheck(_Env())
    obs = np.zeros(3, np.float32)
    assert check.reset((obs, {})) is None and check.step((obs, 0.0, False, False, {})) is None
    assert check.reset(obs) == ("it returned an array of shape (3,) and dtype float32, not a tuple (observation, info) "
                                "(Gymnasium's reset returns both)")
    assert check.reset((obs, {}, 1)) == "it returned 3 values, not 2 (observation, info)"
    assert check.step((obs, 0.0, False, {})) == ("it returned 4 values (the old Gym API: observation, reward, done, info), not 5 "
                                                 "(observation, reward, terminated, truncated, info)")
    assert check.step([obs, 0.0, False, False, {}]) == ("it returned a list of 5, not a tuple (observation, reward, terminated, "
                                                        "truncated, info)")
    assert check.step((obs, 0.0, False, None, {})) == "truncated None is not a bool"
    assert check.step((obs, 0.0, False, False, None)) == "info None is not a dict"
