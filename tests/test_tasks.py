"""The task suite: the paper's ten configurations, their descriptions, generic Gymnasium tasks, extras."""

from __future__ import annotations

import importlib.util
import json
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.errors import ConfigError, UnknownTaskError
from ppprops.evaluation import make_policy, run_episode
from ppprops.tasks import generic_task, get_task, list_tasks
from ppprops.tasks.base import Task

LOCOMOTION = ["reward_forward", "reward_survive", "reward_ctrl", "reward_contact"]
HIGHWAY = ["high_speed_reward", "right_lane_reward", "collision_reward", "on_road_reward"]

# The paper's Table "Evaluated environments": name, env, n_s, n_a, D, action type, reward components.
TABLE = [
    ("Ant-Ultra", "Ant-v5", 10, 8, 88, "continuous", LOCOMOTION),
    ("Ant-Joints", "Ant-v5", 16, 8, 136, "continuous", LOCOMOTION),
    ("Ant-Torso", "Ant-v5", 27, 8, 224, "continuous", LOCOMOTION),
    ("Humanoid-Ultra", "Humanoid-v5", 11, 17, 204, "continuous", LOCOMOTION),
    ("Humanoid-Joints", "Humanoid-v5", 26, 17, 459, "continuous", LOCOMOTION),
    ("Humanoid-Torso", "Humanoid-v5", 45, 17, 782, "continuous", LOCOMOTION),
    ("Acrobot", "Acrobot-v1", 6, 3, 21, "discrete", []),
    ("CartPole", "CartPole-v1", 4, 2, 10, "discrete", []),
    ("FetchReachDense", "FetchReachDense-v4", 6, 4, 28, "continuous", []),
    ("Highway", "highway-v0", 15, 5, 80, "discrete", HIGHWAY),
]
PRESETS = {"Highway-Fast"}  # documented extra presets, listed beside the ten

EXTRA_OF = {"Ant-v5": "mujoco", "Humanoid-v5": "mujoco", "FetchReachDense-v4": "gymnasium_robotics", "highway-v0": "highway_env"}


def _installed(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def _needs(env_id: str) -> list[pytest.MarkDecorator]:
    """The test command installs every simulator extra: a missing one fails the test, never skips it."""
    return []


def test_envs_json_matches_the_paper_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["envs", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert set(rows) == {t[0] for t in TABLE} | PRESETS
    for name, env_id, n_s, n_a, D, action_type, components in TABLE:
        r = rows[name]
        assert (r["env_id"], r["n_s"], r["n_a"], r["D"], r["action_type"]) == (env_id, n_s, n_a, D, action_type), name
        assert r["components"] == components, name
        assert D == (n_s + 1) * n_a


def test_descriptions_cover_every_state_action_component_and_diagnostic() -> None:
    for task in list_tasks():
        text = task.text
        assert len(text.observations) == task.n_s == len(task.observation.names), task.name
        assert len(set(task.observation.names)) == task.n_s, task.name
        assert len(text.actions) == task.n_a, task.name
        assert set(task.components) <= set(text.components), task.name
        assert set(task.diagnostics) <= set(text.diagnostics), task.name
        assert text.summary and text.reward_structure and text.reward_hint, task.name
        # the hint is shown even when the numeric reward structure is withheld: no numbers in it
        assert not re.search(r"\d", text.reward_hint), (task.name, text.reward_hint)


@pytest.mark.parametrize(
    "name",
    [pytest.param(row[0], marks=_needs(row[1]) + ([pytest.mark.slow] if row[0] == "Highway" else [])) for row in TABLE]
    + [pytest.param("Highway-Fast", marks=_needs("highway-v0"))],
)
def test_task_runs_an_episode_with_a_random_policy(name: str) -> None:
    task = get_task(name)
    env = task.make_env()
    try:
        assert _flat_dim(env.action_space) == task.n_a
        obs, _ = env.reset(seed=3)
        s = task.observation(obs)
        assert s.shape == (task.n_s,) and np.all(np.isfinite(s))
        theta = np.random.default_rng(7).uniform(-0.5, 0.5, task.D)
        ep = run_episode(task, env, make_policy(task, theta, env), seed=3)
    finally:
        env.close()
    assert list(ep.components) == list(task.components)
    assert set(task.diagnostics) <= set(ep.diagnostics)
    assert ep.diagnostics["episode_length"] >= 1
    assert "numerical_fault" not in ep.diagnostics
    if task.components:  # the components are the return, split: they must add up to it
        assert sum(ep.components.values()) == pytest.approx(ep.ret, rel=1e-9, abs=1e-9)


def _flat_dim(space: object) -> int:
    return int(getattr(space, "n", 0)) or int(np.prod(space.shape))  # type: ignore[attr-defined]


@pytest.mark.parametrize("robot", ["Ant", "Humanoid"])
def test_locomotion_indices_match_mujoco_joint_layout(robot: str) -> None:
    """Each state name sits where MuJoCo puts that quantity, and the subsets nest Ultra < Joints < Torso."""
    import mujoco

    torso, joints, ultra = (get_task(f"{robot}-{c}") for c in ("Torso", "Joints", "Ultra"))
    env = torso.make_env()
    try:
        env.reset(seed=0)
        obs, *_ = env.step(env.action_space.sample())
        model, data = env.unwrapped.model, env.unwrapped.data
        n_pos = model.nq - 2  # the observation skips the torso's x, y
        expected = {"torso_z": 0, "torso_qw": 1, "torso_qx": 2, "torso_qy": 3, "torso_qz": 4}
        expected.update({f"torso_{v}": n_pos + i for i, v in enumerate(("vx", "vy", "vz", "wx", "wy", "wz"))})
        for j in range(1, model.njnt):
            jname = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            expected[jname] = int(model.jnt_qposadr[j]) - 2
            expected[f"{jname}_vel"] = n_pos + int(model.jnt_dofadr[j])
        names = torso.observation.names
        assert len(names) == len(obs) == model.nq - 2 + model.nv
        assert {n: i for i, n in enumerate(names)} == expected
        np.testing.assert_array_equal(obs, np.concatenate([data.qpos[2:], data.qvel]).astype(obs.dtype))
        # action j of the description names the joint actuator j drives
        for a in range(model.nu):
            jname = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(model.actuator_trnid[a][0]))
            assert re.match(rf"torque on {jname}( |$)", torso.text.actions[a]), (a, jname)
    finally:
        env.close()
    for small, big in ((ultra, joints), (joints, torso)):
        assert set(small.observation.names) < set(big.observation.names)
        idx = small.observation.indices
        assert idx is not None and [names[i] for i in idx] == list(small.observation.names)
        np.testing.assert_array_equal(small.observation(obs), obs[list(idx)].astype(np.float64))
    for task in (ultra, joints, torso):  # same state, same words in every configuration
        for n, line in zip(task.observation.names, task.text.observations, strict=True):
            assert line == torso.text.observations[names.index(n)]


_ANT_LEGS = [f"{j}_{k}" for k in range(1, 5) for j in ("hip", "ankle")]
_LEGS = [f"{side}_{j}" for side in ("right", "left") for j in ("hip_x", "hip_z", "hip_y", "knee")]
CHOSEN = {  # the documented choices (docs/tasks.md): a change here is a change of the task
    "Ant-Ultra": {"torso_z", "torso_vx", *_ANT_LEGS},
    "Ant-Joints": {"torso_z", "torso_vx", *_ANT_LEGS, "torso_qx", "torso_qy", *(f"hip_{k}_vel" for k in range(1, 5))},
    "Humanoid-Ultra": {
        "torso_z",
        "torso_qx",
        "torso_qy",
        "torso_vx",
        "torso_wx",
        "torso_wy",
        "abdomen_y",
        "right_hip_y",
        "right_knee",
        "left_hip_y",
        "left_knee",
    },
    "Humanoid-Joints": {
        "torso_z",
        "torso_qx",
        "torso_qy",
        "torso_vx",
        "torso_wx",
        "torso_wy",
        "abdomen_y",
        "abdomen_x",
        "abdomen_y_vel",
        "abdomen_x_vel",
        *_LEGS,
        *(f"{n}_vel" for n in _LEGS),
    },
}


@pytest.mark.parametrize("name", sorted(CHOSEN))
def test_observation_subsets_are_the_documented_ones(name: str) -> None:
    assert set(get_task(name).observation.names) == CHOSEN[name]


def test_highway_components_split_the_env_reward() -> None:
    from ppprops.tasks.highway import split_reward

    terms = {"collision_reward": 0.0, "right_lane_reward": 1.0, "high_speed_reward": 1.0, "on_road_reward": 1.0}
    assert sum(split_reward(terms).values()) == pytest.approx(1.0)  # the best step
    crash = dict(terms, collision_reward=1.0, right_lane_reward=0.0, high_speed_reward=0.0)
    assert sum(split_reward(crash).values()) == pytest.approx(0.0)
    off_road = dict(terms, on_road_reward=0.0)
    assert all(v == 0.0 for v in split_reward(off_road).values())
    fast = get_task("Highway-Fast")
    assert fast.env_kwargs["config"]["simulation_frequency"] == 5
    from ppprops.tasks.highway import REWARD_CONFIG

    for name in ("Highway", "Highway-Fast"):  # the recorder's weights are the task files' weights
        config = get_task(name).env_kwargs["config"]
        assert {k: config[k] for k in REWARD_CONFIG} == dict(REWARD_CONFIG), name
    assert get_task("highway-v0") is get_task("Highway")


def test_fetch_observation_keeps_gripper_and_goal() -> None:
    fetch = get_task("FetchReachDense")
    obs = {
        "observation": np.arange(10.0),
        "achieved_goal": np.array([-1.0, -2.0, -3.0]),
        "desired_goal": np.array([7.0, 8.0, 9.0]),
    }
    np.testing.assert_array_equal(fetch.observation(obs), [0.0, 1.0, 2.0, 7.0, 8.0, 9.0])


# --- generic Gymnasium ids ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("env_id", "n_s", "n_a", "action_type"),
    [("MountainCarContinuous-v0", 2, 1, "continuous"), ("Pendulum-v1", 3, 1, "continuous"), ("MountainCar-v0", 2, 3, "discrete")],
)
def test_generic_task_for_any_gymnasium_id(env_id: str, n_s: int, n_a: int, action_type: str) -> None:
    task = get_task(env_id)
    assert (task.name, task.env_id, task.n_s, task.n_a, task.action_type) == (env_id, env_id, n_s, n_a, action_type)
    assert task.optimal_return is None and task.components == ()
    assert env_id in task.text.summary and len(task.text.observations) == n_s and len(task.text.actions) == n_a
    env = task.make_env()
    try:
        ep = run_episode(task, env, make_policy(task, np.full(task.D, 0.1), env), seed=0)
    finally:
        env.close()
    assert ep.diagnostics["episode_length"] >= 1 and np.isfinite(ep.ret)


def test_generic_task_reports_declared_info_keys() -> None:
    task = generic_task("Swimmer-v5", components=("reward_forward", "reward_ctrl"), diagnostics=("x_position",))
    assert task.components == ("reward_forward", "reward_ctrl")
    assert task.diagnostics == ("episode_length", "x_position")
    assert "reward_forward" in task.text.components["reward_forward"]
    env = task.make_env()
    try:
        ep = run_episode(task, env, make_policy(task, np.full(task.D, 0.05), env), seed=0)
    finally:
        env.close()
    assert sum(ep.components.values()) == pytest.approx(ep.ret)  # Swimmer's reward is exactly these two
    assert isinstance(ep.diagnostics["x_position"], float)


def test_dict_observation_needs_chosen_keys() -> None:
    with pytest.raises(ConfigError, match=r"Dict observation \(achieved_goal, desired_goal, observation\); choose .* --obs-keys"):
        get_task("FetchReach-v4")  # the sparse Fetch env: registered by the plugin, not a ppprops task


def test_unknown_and_ambiguous_ids() -> None:
    with pytest.raises(UnknownTaskError, match="CartPole"):
        get_task("CartPol-v1")
    with pytest.raises(UnknownTaskError, match="Ant-Ultra, Ant-Joints, Ant-Torso"):
        get_task("Ant-v5")
    assert get_task("cartpole-v1") is get_task("CartPole")
    with pytest.raises(ConfigError):
        generic_task("Pendulum-v1", components=("x",), diagnostics=("x",))


def test_tasks_list_and_missing_extras_without_simulators() -> None:
    """With the simulators unimportable, listing still works and making an env names the extra."""
    script = textwrap.dedent(
        """
        import sys
        for m in ("mujoco", "highway_env", "gymnasium_robotics"):
            sys.modules[m] = None  # any import of it now raises ImportError
        import json, io, contextlib
        import numpy as np
        from ppprops.cli import main
        from ppprops.errors import MissingExtraError
        from ppprops.evaluation import Evaluator
        from ppprops.tasks import get_task
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert main(["envs", "--json"]) == 0
        print(len(json.loads(out.getvalue())))
        for name in ("Ant-Torso", "Humanoid-Ultra", "FetchReachDense", "Highway"):
            try:
                get_task(name).make_env()
            except MissingExtraError as e:
                print(name, e.extra)
        try:
            Evaluator(get_task("Ant-Ultra"), workers=2).evaluate(np.zeros(88), [0, 1])
        except MissingExtraError as e:
            print("pool", e.extra)
        """
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split("\n")[:6] == [
        str(len(TABLE) + len(PRESETS)),
        "Ant-Torso mujoco",
        "Humanoid-Ultra mujoco",
        "FetchReachDense robotics",
        "Highway highway",
        "pool mujoco",
    ]


def test_task_objects_are_frozen() -> None:
    task = get_task("CartPole")
    assert isinstance(task, Task)
    with pytest.raises(AttributeError):
        task.n_s = 5  # type: ignore[misc]
