"""Parallel evaluation gives exactly the serial results: same episodes, same order, same floats."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from ppprops.errors import ConfigError
from ppprops.evaluation import Evaluator, Feedback
from ppprops.tasks import generic_task, get_task, resolve_task, task_ref
from ppprops.tasks.base import Task


def _installed(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def _thetas(task: Task, n: int, seed: int = 0, scale: float = 0.3) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.uniform(-scale, scale, task.D) for _ in range(n)]


def _same(a: Feedback, b: Feedback) -> None:
    assert a == b  # dataclass equality: floats compared exactly
    assert repr(a.to_json()) == repr(b.to_json())


def _serial_and_parallel(
    task: Task, thetas: list[np.ndarray], seeds_list: list[list[int]]
) -> tuple[list[Feedback], list[Feedback]]:
    with Evaluator(task) as serial, Evaluator(task, workers=2) as parallel:
        want = [serial.evaluate(th, seeds) for th, seeds in zip(thetas, seeds_list, strict=True)]
        got = parallel.evaluate_many(thetas, seeds_list)
        # and the single-candidate call, on a pool whose envs already ran other episodes
        got_one = parallel.evaluate(thetas[-1], seeds_list[-1])
    _same(got_one, want[-1])
    return want, got


TASKS = [
    pytest.param("CartPole", id="CartPole"),
    pytest.param("Acrobot", id="Acrobot"),
    pytest.param("Ant-Ultra", id="Ant-Ultra"),
    pytest.param("Humanoid-Torso", id="Humanoid-Torso"),
    pytest.param(
        "FetchReachDense", id="Fetch"
    ),
    pytest.param("Highway-Fast", id="Highway-Fast"),
]


@pytest.mark.parametrize("name", TASKS)
def test_parallel_equals_serial(name: str) -> None:
    task = get_task(name)
    thetas = _thetas(task, 3)
    # highway episodes cost seconds: fewer of them there
    seeds_list = [[0], [5], [9]] if task.env_id == "highway-v0" else [[0, 1], [5], [9, 1, 4]]
    want, got = _serial_and_parallel(task, thetas, seeds_list)
    assert len(got) == len(want) == 3
    for a, b, seeds in zip(want, got, seeds_list, strict=True):
        _same(a, b)
        assert len(b.episode_returns) == len(seeds)
    # the check can fail: other seeds give other results on these tasks
    with Evaluator(task) as ev:
        other = ev.evaluate(thetas[0], [11])
    assert other.episode_returns != want[0].episode_returns[:1]


def test_parallel_equals_serial_for_a_generic_task() -> None:
    task = generic_task("Pendulum-v1")
    thetas = _thetas(task, 2)
    want, got = _serial_and_parallel(task, thetas, [[0, 1], [2, 3]])
    for a, b in zip(want, got, strict=True):
        _same(a, b)


def test_task_refs_rebuild_the_same_task() -> None:
    assert task_ref(get_task("CartPole")) == "CartPole"
    assert resolve_task(task_ref(get_task("Highway-Fast"))) is get_task("Highway-Fast")
    generic = generic_task("Swimmer-v5", components=("reward_forward",), diagnostics=("x_position",))
    ref = task_ref(generic)
    assert isinstance(ref, dict) and ref["name"] == "Swimmer-v5"  # the declaration as JSON values, not the task itself
    rebuilt = resolve_task(ref)
    assert rebuilt.summary() == generic.summary() and rebuilt.components == ("reward_forward",)


def test_bad_arguments() -> None:
    task = get_task("CartPole")
    with pytest.raises(ConfigError):
        Evaluator(task, workers=0)
    with Evaluator(task) as ev, pytest.raises(ConfigError):
        ev.evaluate_many([np.zeros(task.D)], [[0], [1]])
