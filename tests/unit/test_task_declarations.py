"""Task declarations: the task file's schema, tasks without an env, no probe
episode at load (the checks run in the first episodes, or in `ppprops task check` when asked),
each task's privacy facts in its file, the display name for the provider, and an env that raises
named in one line."""

from __future__ import annotations

import json
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import ppprops
from ppprops.cli import main
from ppprops.client.hardening import residual_component, return_determining, reward_scale
from ppprops.errors import ConfigError
from ppprops.evaluation import make_policy, run_episode
from ppprops.fileio import write_json_atomic
from ppprops.policy_file import load_policy, policy_document
from ppprops.privacy.knowledge import facts_for
from ppprops.tasks import (
    EnvError,
    FeedbackKeyError,
    NoEnvError,
    TaskFileError,
    check_task,
    describe_user_error,
    get_task,
    load_task,
    privacy_facts,
    task_from_json,
)
from ppprops.tasks.facts import Cap
from ppprops.tasks.options import TaskOptions

ROOT = Path(__file__).resolve().parents[2]
ROBOT = ROOT / "examples" / "robot_outside" / "robot.toml"

# Envs of a user's module; each counts how often it was made, reset and stepped.
MODULE = '''
import gymnasium as gym
import numpy as np
from gymnasium import spaces


class Counting(gym.Env):
    """Ends after 5 steps; info holds one scalar, one dict and one string."""

    made = resets = steps = 0

    def __init__(self):
        Counting.made += 1
        self.observation_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float64)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float64)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        Counting.resets += 1
        self.t = 0
        return np.zeros(3), {}

    def step(self, action):
        Counting.steps += 1
        self.t += 1
        info = {"effort": 1.0, "parts": {"a": 1.0, "b": 2.0}, "mode": "fine"}
        return np.zeros(3), 1.0, False, self.t >= 5, info


class FaultyDriver(gym.Env):
    observation_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float64)
    action_space = spaces.Discrete(2)

    def __init__(self, broken_at="step"):
        if broken_at == "init":
            raise RuntimeError("motor driver fault")
        self.broken_at = broken_at

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2), {}

    def step(self, action):
        raise RuntimeError("motor driver fault")
'''


@pytest.fixture
def user_module(tmp_path: Path) -> Iterator[str]:
    """A fresh module of user envs on sys.path (a new name per test: nothing cached between tests)."""
    name = f"ppt_envs_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{name}.py").write_text(MODULE)
    sys.path.insert(0, str(tmp_path))
    yield name
    sys.path.remove(str(tmp_path))
    sys.modules.pop(name, None)


def _counts(module: str) -> tuple[int, int, int]:
    c = sys.modules[module].Counting
    return c.made, c.resets, c.steps


def _line(capsys: pytest.CaptureFixture[str], args: list[str]) -> tuple[int, str, str]:
    code = main(args)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


# -- no probe episode at load -----------------------------------------------------------------------
def test_loading_a_task_makes_its_env_once_and_never_resets_or_steps_it(tmp_path: Path, user_module: str) -> None:
    f = tmp_path / "t.toml"
    f.write_text(f'name = "C"\nenv = "{user_module}:Counting"\n[components]\neffort = "effort"\n'
                 '[diagnostics]\nmode = { info = "mode" }\n')  # fmt: skip
    task = load_task(f)
    assert (task.n_s, task.n_a, task.components) == (3, 1, ("effort",))
    assert _counts(user_module) == (1, 0, 0)  # made once to read its spaces; no reset, no step
    load_task(f"{user_module}:Counting", options=TaskOptions(components=["effort"], diagnostics=["mode"]))
    assert _counts(user_module) == (2, 0, 0)
    result = check_task(f)  # the check the user asks for does step it
    assert result.ok and result.steps == 5 and result.ended and _counts(user_module) == (3, 1, 5)


def test_the_first_episode_checks_the_declared_keys(user_module: str) -> None:
    """What the probe checked at load, every episode checks now: a component at the first step, a
    diagnostic at some step; each one line naming the key and the keys there are."""
    env_id = f"{user_module}:Counting"
    for kwargs, line in [
        ({"components": ["efort"]}, f"{env_id}: component 'efort' is not in the env's info at the first step (its keys: effort, "
                                    "parts, mode); did you mean effort?"),
        ({"diagnostics": ["phase"]}, f"{env_id}: diagnostic 'phase' is not in the env's info at any step of an episode (its "
                                     "keys: effort, parts, mode); did you mean parts?"),
    ]:  # fmt: skip
        task = load_task(env_id, options=TaskOptions(**kwargs))
        env = task.make_env()
        try:
            with pytest.raises(FeedbackKeyError) as e:
                run_episode(task, env, make_policy(task, np.zeros(task.D), env), seed=0)
        finally:
            env.close()
        assert str(e.value) == line


def test_task_check_reports_every_problem_at_once(user_module: str) -> None:
    env_id = f"{user_module}:Counting"
    result = check_task(env_id, options=TaskOptions(components=["efort", "parts"], diagnostics=["phase", "mode"]))
    assert not result.ok and result.checked is None and result.steps == 5 and result.ended
    assert list(result.problems) == [
        f"{env_id}: component 'efort' is not in the env's info at the first step (its keys: effort, parts, mode); did you "
        "mean effort?",
        f"{env_id}: component 'parts' is a dict in the env's info (a, b), not a number; name an entry (--component parts.a), "
        "or list them all with `ppprops task check` and --component 'parts.*'",
        f"{env_id}: diagnostic 'phase' is not in the env's info at any step of an episode (its keys: effort, parts, mode); did "
        "you mean parts?",
    ]  # fmt: skip
    expanded = check_task(env_id, options=TaskOptions(components=["parts.*"]))
    assert expanded.ok and expanded.expanded == {"parts.*": ("parts.a", "parts.b")}
    assert expanded.checked is not None and expanded.checked.components == ("parts.a", "parts.b")
    with pytest.raises(TaskFileError, match=r"component 'parts\.\*' asks for every entry .* `ppprops task check`"):
        load_task(env_id, options=TaskOptions(components=["parts.*"]))


def test_task_check_cli(capsys: pytest.CaptureFixture[str], user_module: str) -> None:
    code, out, err = _line(capsys, ["task", "check", "--env", f"{user_module}:Counting", "--component", "effort", "--json"])
    assert code == 0 and err == ""
    doc = json.loads(out)
    assert (doc["ok"], doc["steps"], doc["ended"], doc["problems"]) == (True, 5, True, [])
    code, out, err = _line(capsys, ["task", "check"])
    assert code == 2 and out == "" and err == "ppprops: error: task check needs one task: a task file, --env ID or --task-file FILE\n"
    code, out, err = _line(capsys, ["task", "check", str(ROBOT)])
    assert code == 0 and out.startswith("task RigArm: no env (a robot outside Python, driven with ask/tell)")


# -- an env that raises: one line naming the user's code ---------------------------------------------
def test_an_env_constructor_that_raises_is_one_line_naming_the_users_frame(tmp_path: Path, user_module: str) -> None:
    path = tmp_path / f"{user_module}.py"
    line_no = MODULE.splitlines().index('            raise RuntimeError("motor driver fault")') + 1
    with pytest.raises(EnvError) as e:
        load_task(f"{user_module}:FaultyDriver", options=TaskOptions(env_kwargs={"broken_at": "init"}))
    assert str(e.value) == (f"making {user_module}:FaultyDriver failed: RuntimeError: motor driver fault "
                            f"(at {path}:{line_no}, in __init__)")  # fmt: skip


def test_an_env_whose_step_raises_loads_and_the_check_names_the_fault(tmp_path: Path, user_module: str) -> None:
    task = load_task(f"{user_module}:FaultyDriver")  # nothing stepped: nothing raised
    assert task.n_a == 2
    result = check_task(f"{user_module}:FaultyDriver")
    step_line = MODULE.splitlines().index('        raise RuntimeError("motor driver fault")') + 1
    assert result.problems == (f"{user_module}:FaultyDriver: the env's step 1 raised RuntimeError: motor driver fault "
                               f"(at {tmp_path / (user_module + '.py')}:{step_line}, in step)",)  # fmt: skip
    assert result.raised and result.lines()[0].endswith("0 steps, the env raised; 1 problem:")


def test_describe_user_error_points_at_the_callers_frame_of_a_standard_library_error() -> None:
    try:
        json.loads("{")
    except ValueError as e:
        line = describe_user_error(e)
    assert line.startswith("JSONDecodeError: Expecting property name enclosed in double quotes") and "(at " in line
    assert __file__ in line  # this test's frame is the innermost one outside the standard library


def test_a_gymnasium_env_with_a_bad_kwarg_loads_and_the_check_says_which_kwargs() -> None:
    load_task("Pendulum-v1", options=TaskOptions(env_kwargs={"g": "heavy"}))  # no probe, so no traceback at load
    result = check_task("Pendulum-v1", options=TaskOptions(env_kwargs={"g": "heavy"}))
    assert result.problems == ("Pendulum-v1: the env's step 1 raised TypeError: unsupported operand type(s) for /: 'str' "
                               "and 'float' (check env_kwargs {\"g\": \"heavy\"})",)  # fmt: skip


# -- a task without env -------------------------------------------------------------------------------
def test_a_task_without_env_declares_what_the_policy_sees_and_does() -> None:
    task = load_task(ROBOT)
    assert not task.has_env and task.env_id == ""
    assert (task.n_s, task.n_a, task.D, task.action_type) == (6, 2, 14, "continuous")
    assert (task.action_low, task.action_high) == ((-2.0, -2.0), (2.0, 2.0))
    low, high = task.action_bounds()  # type: ignore[misc]
    np.testing.assert_array_equal(low, [-2.0, -2.0])
    np.testing.assert_array_equal(high, [2.0, 2.0])
    assert task.components == ("reward_distance", "reward_effort") and task.diagnostics == ("final_distance", "reached")
    assert task.observation.names == ("shoulder", "elbow", "shoulder_vel", "elbow_vel", "dx", "dy")
    assert task.prompt_name == "a two-joint arm" and task.name == "RigArm"
    line = ("task RigArm has no env: it describes a robot outside Python, whose episodes only its own driver runs; search it "
            "with ask/tell (`ppprops ask` / `ppprops tell`, or Study.ask / Study.tell), and evaluate its policy on the robot")  # fmt: skip
    with pytest.raises(NoEnvError) as e:
        task.make_env()
    assert str(e.value) == line
    assert task_from_json(json.loads(json.dumps(task.spec.model_dump(mode="json")))) == task  # stored and rebuilt in any process
    with pytest.raises(TaskFileError, match="task RigArm has no env .* apply to an env"):
        load_task(ROBOT, options=TaskOptions(components=["x"]))


def test_generic_prose_names_nothing_of_the_user(tmp_path: Path, user_module: str) -> None:
    """A task file without a summary gets generic prose that names no module, class or task of the user."""
    f = tmp_path / "acme_secret_arm.toml"
    f.write_text('name = "AcmeSecretArm"\naction_type = "discrete"\nactions = ["left", "right"]\n'
                 '[observation.values]\nx = "position"\n[diagnostics]\nreached = ""\n')  # fmt: skip
    for task in (load_task(f), load_task(f"{user_module}:Counting")):
        assert task.prompt_name is None
        assert task.text.summary.startswith("A robot or environment with no public name.")
        assert not any(word in task.text.summary.lower() for word in ("acme", "ppt_envs", "counting"))
    assert load_task(f).diagnostics == ("reached",)
    assert load_task("Pendulum-v1").text.summary.startswith("The Gymnasium environment Pendulum-v1.")  # a public id may be named


def test_the_policy_file_of_a_task_without_env(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    task = load_task(ROBOT)
    theta = np.arange(task.D, dtype=float) / 3.0
    doc = policy_document(task, theta, env=None, search={}, final_eval=None)
    assert doc["env"] is None and doc["env_id"] is None
    assert doc["action"] == {"type": "continuous", "rule": "clip", "low": [-2.0, -2.0], "high": [2.0, 2.0]}
    path = tmp_path / "best_policy.json"
    write_json_atomic(path, doc)
    policy = load_policy(path)
    obs = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.05])
    W, b = theta[:12].reshape(6, 2), theta[12:]
    np.testing.assert_array_equal(policy(obs), np.clip(obs @ W + b, -2.0, 2.0))
    with pytest.raises(ConfigError, match="task RigArm has no env"):
        policy.make_env()
    code, out, err = _line(capsys, ["policy", "eval", str(path), "--episodes", "2", "--quiet"])
    assert code == 2 and out == "" and err.count("\n") == 1 and err.startswith("ppprops: error: task RigArm has no env: ")
    with pytest.raises(NoEnvError):  # worker processes are refused before a pool starts
        ppprops.evaluate_policy(policy, episodes=2, workers=2)


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ('name = "R"\naction_type = "continuous"\nactions = ["a"]\n[observation.values]\nx = "x"\n',
         "a task without env must give action_low and action_high for continuous actions (a number for every action, or a "
         "list with one per action)"),
        ('name = "R"\naction_type = "continuous"\nactions = ["a", "b"]\naction_low = [-1.0]\naction_high = 1.0\n'
         '[observation.values]\nx = "x"\n',
         "action_low must be a number or a list of 2 numbers (one per action), got [-1.0]"),
        ('name = "R"\naction_type = "continuous"\nactions = ["a"]\naction_low = 1.0\naction_high = -1.0\n[observation.values]\nx = "x"\n',
         "action 0 has action_low 1 > action_high -1"),
        ('name = "R"\naction_type = "discrete"\nactions = ["a"]\nmax_episode_steps = 9\n[observation.values]\nx = "x"\n',
         "max_episode_steps needs an env, and this task has none (no env key): a task without env declares only what the "
         "policy sees (observation.values) and does (action_type, actions)"),
        ('name = "R"\naction_type = "discrete"\nactions = ["a"]\n[observation.values]\nx = "x"\n[diagnostics]\nd = { info = "k" }\n',
         "diagnostics.d.info reads an env's info, and this task has none: its feedback is what the robot's driver tells "
         "(name = \"meaning\")"),
        ('name = "R"\nenv = "CartPole-v1"\naction_low = -1.0\n',
         "action_low and action_high are read from the env's action space: give them only in a task without env"),
        ('name = "R"\nenv = "CartPole-v1"\n[observation]\nindice = [0]\n', "unknown key 'observation.indice' (did you mean indices?)"),
        ('name = "R"\nenv = "CartPole-v1"\nmax_episode_steps = 0\n', "max_episode_steps must be a positive integer, got 0"),
        ('name = "R"\nenv = "CartPole-v1"\nmax_episode_steps = true\n', "max_episode_steps must be a positive integer, got True"),
        ('name = "R"\nenv = "CartPole-v1"\noptimal_return = "high"\n', "optimal_return must be a number, got 'high'"),
        ('name = "R"\nenv = "CartPole-v1"\nprompt_name = " "\n',
         "prompt_name must be a non-empty string (the name the prompt may show), got ' '"),
        ('name = "R"\nenv = "CartPole-v1"\n[components]\nx = 5\n',
         'components.x must be a string or a table (name = "meaning" or name = { info = KEY, ... }), got 5'),
        ('name = "R"\nenv = "CartPole-v1"\n[privacy]\npublic = true\n', "unknown key 'privacy.public' (did you mean public_env?)"),
        ('name = "R"\nenv = "CartPole-v1"\n[privacy]\nsurvive_component = 3\n',
         "privacy.survive_component must be a component name, or false, got 3"),
        ('name = "R"\nenv = "CartPole-v1"\n[privacy]\nsurvive_component = "reward_x"\n',
         "privacy.survive_component names component 'reward_x', which this task does not declare (it has: none declared)"),
        ('name = "R"\nenv = "CartPole-v1"\n[privacy]\ncaps = [{ side = "up", value = 1.0, diagnostic = "episode_length", marker = "x" }]\n',
         "privacy.caps.side must be max or min, got 'up'"),
        ('name = "R"\nenv = "CartPole-v1"\n[privacy]\ncaps = [{ sid = "max" }]\n', "unknown key 'privacy.caps.sid' (did you mean side?)"),
        ('name = "R"\nenv = "CartPole-v1"\ncomponents = 5\n', "components must be a table, got 5"),
        ('env = "CartPole-v1"\n', "name is required"),
        ('name = "R"\nenv = "CartPole-v1"\n[privacy]\nhealthy_reward = 1.0\n', "privacy.healthy_reward needs privacy.survive_component"),
        ('name = "R"\nenv = "CartPole-v1"\n[components]\nc = "c"\n[privacy]\nresidual_component = false\n',
         "privacy.residual_component is false, but the task has components: name the one pp-hardened leaves out (with every "
         "component shown, their sum gives the reward secrets away)"),
    ],
)  # fmt: skip
def test_task_file_errors_are_one_line_naming_the_key(tmp_path: Path, text: str, line: str) -> None:
    f = tmp_path / "t.toml"
    f.write_text(text)
    with pytest.raises(TaskFileError) as e:
        load_task(f)
    assert str(e.value) == f"task file {f}: {line}"


# -- stored declarations of earlier runs --------------------------------------------------------------
# The declaration ppprops stored for `--env Pendulum-v1` before this change (ppprops.task/1).
OLD_PENDULUM = {
    "format": "ppprops.task/1", "name": "Pendulum-v1",
    "env": {"id": "Pendulum-v1", "entry_point": "gymnasium.envs.classic_control.pendulum:PendulumEnv", "kwargs": {},
            "max_episode_steps": 200, "imports": [], "paths": [], "setup": None},
    "observation": {"keys": None, "indices": None, "one_hot": None, "names": ["obs_0", "obs_1", "obs_2"],
                    "descriptions": ["observed value 0 of the environment's flattened observation (range -1 to 1)",
                                     "observed value 1 of the environment's flattened observation (range -1 to 1)",
                                     "observed value 2 of the environment's flattened observation (range -8 to 8)"]},
    "action_type": "continuous", "actions": ["actuation 0 (range -2 to 2)"], "components": [], "diagnostics": [],
    "recorder": None,
    "summary": "The Gymnasium environment Pendulum-v1. No description of its physics or goal is available: what the 3 observed "
               "values and the 1 policy outputs mean has to be inferred from the feedback.",
    "reward_structure": "The return is the sum of the environment's per-step rewards over an episode.",
    "reward_hint": "The return is the sum of the environment's per-step rewards over an episode; higher is better.",
    "hints": "Nothing is known about the task beyond the feedback; start with small weights and change few parameters at a time "
             "to learn what each one does.",
    "optimal_return": None,
}  # fmt: skip


def test_declarations_stored_before_still_read_and_are_written_the_same() -> None:
    task = task_from_json(OLD_PENDULUM)
    assert task == load_task("Pendulum-v1") and task.spec.model_dump(mode="json") == OLD_PENDULUM
    assert task.spec.privacy is None and facts_for(task).public_env  # a plain Gymnasium id: an attacker can simulate it
    # a paper task's declaration stored before [privacy] existed gets the paper task's facts, and only when it is that task
    old = get_task("CartPole").spec.model_dump(mode="json")
    del old["privacy"]
    assert privacy_facts(task_from_json(old)) == get_task("CartPole").spec.privacy
    assert privacy_facts(task_from_json({**old, "summary": "another cart"})).is_empty()


# Declarations exactly as ppprops stored them (ppprops.task/1) before the declaration became one
# pydantic model: what TaskSpec.to_json wrote then, hard-coded. A paper task (its recorder, its
# [privacy] facts with a cap), a task without env (action bounds and prompt_name, written only when
# set) and a Gymnasium id with a Discrete observation (one_hot as {n, start}, env kwargs pinned).
STORED_CARTPOLE = {
    "format": "ppprops.task/1",
    "name": "CartPole",
    "env": {"id": "CartPole-v1", "entry_point": None, "kwargs": {}, "max_episode_steps": None, "imports": [], "paths": [], "setup": None},
    "observation": {"keys": None, "indices": None, "one_hot": None,
                    "names": ["cart_position", "cart_velocity", "pole_angle", "pole_angular_velocity"],
                    "descriptions": ["cart position along the track (0 is the centre)", "cart velocity",
                                     "pole angle from vertical (positive leans right)", "pole angular velocity"]},
    "action_type": "discrete",
    "actions": ["score for pushing the cart to the left", "score for pushing the cart to the right"],
    "components": [],
    "diagnostics": [{"name": "episode_length", "description": "steps the episode lasted", "info": None, "reduce": "last"},
                    {"name": "termination", "description": "why the episode ended: pole_fell, cart_out_of_bounds or time_limit",
                     "info": None, "reduce": "last"}],
    "recorder": "ppprops.tasks.classic:CartPoleRecorder",
    "summary": "A pole is attached by an unactuated joint to a cart that moves along a frictionless track. The controller pushes the cart "
               "left or right at every step; the goal is to keep the pole upright and the cart on the track for as long as possible.",
    "reward_structure": "The reward is +1 for every step the pole stays up. An episode ends when the pole leans more than 12 degrees, the "
                        "cart leaves the track (|position| > 2.4), or after 500 steps.",
    "reward_hint": "The return grows with the time the pole is kept balanced and the cart kept on the track.",
    "hints": "The action with the higher score is applied. A balancing controller pushes the cart towards the side the pole is falling "
             "to; the angle and angular velocity matter most.",
    "optimal_return": 500.0,
    "prompt_name": "CartPole",
    "privacy": {"integer_returns": True, "return_formula": {"episode_length": 1.0},
                "caps": [{"side": "max", "value": 500.0, "diagnostic": "termination", "marker": "time_limit"}],
                "return_range": [1.0, 500.0], "resolution": {"return": 1.0}, "survive_component": False, "ctrl_component": False,
                "time_limit": 500, "components_sum_to_return": False, "return_determining": ["episode_length"],
                "residual_component": False, "reward_scale": 500.0},
}  # fmt: skip
STORED_RIGARM = {
    "format": "ppprops.task/1",
    "name": "RigArm",
    "env": None,
    "observation": {"keys": None, "indices": None, "one_hot": None,
                    "names": ["shoulder", "elbow", "shoulder_vel", "elbow_vel", "dx", "dy"],
                    "descriptions": ["shoulder angle (rad, 0 points along +x)", "elbow angle relative to the upper link (rad)",
                                     "shoulder angular velocity (rad/s)", "elbow angular velocity (rad/s)", "target x minus tip x (m)",
                                     "target y minus tip y (m)"]},
    "action_type": "continuous",
    "actions": ["shoulder torque (N m, -2 to 2; positive turns the upper link counter-clockwise)",
                "elbow torque (N m, -2 to 2; positive turns the forearm counter-clockwise)"],
    "components": [{"name": "reward_distance", "description": "minus the tip-to-target distance, summed over the steps", "info": None,
                    "reduce": "sum"},
                   {"name": "reward_effort", "description": "minus the torque cost, summed over the steps", "info": None, "reduce": "sum"}],
    "diagnostics": [{"name": "final_distance", "description": "distance from the tip to the target at the end of the trial (m)",
                     "info": None, "reduce": "last"},
                    {"name": "reached", "description": "1 if the tip ended within 1 cm of the target, else 0", "info": None,
                     "reduce": "last"}],
    "recorder": None,
    "summary": "A planar arm with two revolute joints (shoulder, elbow) moves its tip towards a target point drawn at random in its "
               "workspace at the start of each trial. The controller sets both joint torques every 10 ms; the goal is to bring the tip to "
               "the target quickly and hold it there, without wasting effort.",
    "reward_structure": "Each step pays minus the distance from the tip to the target (m) minus 0.01 times the sum of the squared torques. "
                        "A trial lasts 200 steps (2 s).",
    "reward_hint": "The return is higher the sooner the tip gets close to the target and the less torque it uses.",
    "hints": "Drive each joint towards the target with a term proportional to the tip's offset from it, and damp it with the joint's "
             "velocity; start with small weights.",
    "optimal_return": None,
    "action_low": [-2.0, -2.0],
    "action_high": [2.0, 2.0],
    "prompt_name": "a two-joint arm",
    "privacy": {"public_env": False, "integer_returns": False, "return_formula": False, "survive_component": False,
                "ctrl_component": "reward_effort", "ctrl_per_step": 0.08, "time_limit": 200, "components_sum_to_return": True,
                "return_determining": [], "residual_component": "reward_effort", "reward_scale": 300.0},
}  # fmt: skip
STORED_FROZEN_LAKE = {
    "format": "ppprops.task/1",
    "name": "FrozenLake-v1",
    "env": {"id": "FrozenLake-v1", "entry_point": "gymnasium.envs.toy_text.frozen_lake:FrozenLakeEnv", "kwargs": {"map_name": "4x4"},
            "max_episode_steps": 100, "imports": [], "paths": [], "setup": None},
    "observation": {"keys": None, "indices": None, "one_hot": {"n": 16, "start": 0}, "names": [f"state_{i}" for i in range(16)],
                    "descriptions": [f"1 when the environment is in discrete state {i}, else 0" for i in range(16)]},
    "action_type": "discrete",
    "actions": [f"score for discrete action {j}" for j in range(4)],
    "components": [],
    "diagnostics": [],
    "recorder": None,
    "summary": "The Gymnasium environment FrozenLake-v1. No description of its physics or goal is available: what the 16 observed values "
               "and the 4 policy outputs mean has to be inferred from the feedback.",
    "reward_structure": "The return is the sum of the environment's per-step rewards over an episode.",
    "reward_hint": "The return is the sum of the environment's per-step rewards over an episode; higher is better.",
    "hints": "Nothing is known about the task beyond the feedback; start with small weights and change few parameters at a time to learn "
             "what each one does.",
    "optimal_return": None,
}  # fmt: skip


@pytest.mark.parametrize(
    ("stored", "source"),
    [(STORED_CARTPOLE, "CartPole"), (STORED_RIGARM, str(ROBOT)), (STORED_FROZEN_LAKE, "FrozenLake-v1")],
    ids=["paper-task", "without-env", "one-hot"],
)
def test_declarations_stored_as_ppprops_task_1_load_and_are_stored_the_same(stored: dict, source: str) -> None:
    name = stored["name"]
    stored = json.loads(json.dumps(stored))  # as read back from run.sqlite or a policy file
    task = task_from_json(stored)
    fresh = load_task(source)
    assert task == fresh and task.spec.complete and task.spec.privacy == (fresh.spec.privacy if "privacy" in stored else None)
    assert task.spec.model_dump(mode="json") == stored and fresh.spec.model_dump(mode="json") == stored  # a run stored now writes the same
    assert task_from_json(json.loads(json.dumps(task.spec.model_dump(mode="json")))) == task
    assert (task.n_s, task.n_a, task.action_type, task.components, task.diagnostics, task.text, task.prompt_name, task.optimal_return) \
        == (fresh.n_s, fresh.n_a, fresh.action_type, fresh.components, fresh.diagnostics, fresh.text, fresh.prompt_name,
            fresh.optimal_return)  # fmt: skip
    assert task.observation == fresh.observation and task.observation.names == tuple(stored["observation"]["names"])
    assert facts_for(task) == facts_for(fresh)
    if name == "CartPole":
        assert task.has_env and task.env_id == "CartPole-v1" and task.optimal_return == 500.0 and task.n_s == 4 and task.discrete
        assert facts_for(task).time_limit == 500 and facts_for(task).return_formula == {"episode_length": 1.0}
        assert reward_scale(task) == 500.0 and return_determining(task) == {"episode_length"}
    elif name == "RigArm":
        assert not task.has_env and task.env_id == "" and task.prompt_name == "a two-joint arm"
        assert task.action_low == (-2.0, -2.0) and task.action_high == (2.0, 2.0) and task.components == ("reward_distance", "reward_effort")
        assert residual_component(task) == {"reward_effort"} and reward_scale(task) == 300.0
    else:
        assert task.observation.one_hot == (16, 0) and task.n_s == 16 and task.n_a == 4 and dict(task.env_kwargs) == {"map_name": "4x4"}
        assert task.spec.env.max_episode_steps == 100 and task.spec.privacy is None and facts_for(task).public_env


# -- privacy facts --------------------------------------------------------------------------------------
# The tables of privacy/knowledge.py and client/hardening.py before the facts moved into the task files,
# as the completed facts read them (``facts_for``): a fact a table did not hold has its neutral value.
NEUTRAL = {"integer_returns": False, "return_formula": {}, "return_formula_constant": 0.0, "caps": [], "return_range": None,
           "resolution": {}, "survive_component": None, "healthy_reward": None, "ctrl_component": None, "ctrl_per_step": None,
           "time_limit": None, "components": (), "components_sum_to_return": False}  # fmt: skip
OLD_FACTS = {
    "CartPole": {**NEUTRAL, "integer_returns": True, "return_formula": {"episode_length": 1.0}, "return_formula_constant": 0.0,
                 "caps": [Cap(side="max", value=500.0, diagnostic="termination", marker="time_limit")], "return_range": [1.0, 500.0],
                 "resolution": {"return": 1.0}, "time_limit": 500},
    "Acrobot": {**NEUTRAL, "integer_returns": True, "return_formula": {"episode_length": -1.0, "success": 1.0},
                "return_formula_constant": 0.0, "caps": [Cap(side="min", value=-500.0, diagnostic="success", marker="0")],
                "return_range": [-500.0, -1.0], "resolution": {"return": 1.0}, "time_limit": 500},
    "Ant": {**NEUTRAL, "resolution": {"reward_survive": 1.0}, "survive_component": "reward_survive", "healthy_reward": 1.0,
            "ctrl_component": "reward_ctrl", "ctrl_per_step": 4.0, "time_limit": 1000,
            "components": ("reward_forward", "reward_survive", "reward_ctrl", "reward_contact"), "components_sum_to_return": True},
    "Humanoid": {**NEUTRAL, "resolution": {"reward_survive": 5.0}, "survive_component": "reward_survive", "healthy_reward": 5.0,
                 "ctrl_component": "reward_ctrl", "ctrl_per_step": 0.272, "time_limit": 1000,
                 "components": ("reward_forward", "reward_survive", "reward_ctrl", "reward_contact"), "components_sum_to_return": True},
}  # fmt: skip
OLD_SCALE = {"CartPole": 500.0, "Acrobot": 500.0, "FetchReachDense": 50.0}
OLD_FIELDS = ("integer_returns", "return_formula", "return_formula_constant", "caps", "return_range", "resolution", "survive_component",
              "healthy_reward", "ctrl_component", "ctrl_per_step", "time_limit", "components", "components_sum_to_return")  # fmt: skip


def test_the_paper_tasks_declare_the_facts_the_tables_held() -> None:
    for task in ppprops.tasks.list_tasks():
        family = task.name.split("-")[0]
        want = OLD_FACTS.get(task.name) or OLD_FACTS.get(family) or NEUTRAL
        got = facts_for(task)
        for name in OLD_FIELDS:
            assert getattr(got, name) == pytest.approx(want[name]) if name == "ctrl_per_step" and got.ctrl_per_step \
                else getattr(got, name) == want[name], (task.name, name)  # fmt: skip
        assert got.public_env and facts_for(task.name) == got
        assert return_determining(task) == {"episode_length"}
        assert reward_scale(task) == OLD_SCALE.get(task.name, 1000.0)
        residual = "reward_survive" if family in ("Ant", "Humanoid") else task.components[0] if task.components else None
        assert residual_component(task) == (frozenset({residual}) if residual else frozenset())
        if family in ("CartPole", "Acrobot", "Ant", "Humanoid"):
            assert got.unknown == (), task.name


def test_a_users_task_declares_its_facts_or_they_are_unknown(tmp_path: Path, user_module: str) -> None:
    bare = load_task(f"{user_module}:Counting", options=TaskOptions(components=["effort"]))
    facts = facts_for(bare)
    assert not facts.public_env and "integer_returns" in facts.unknown and "reward_scale" in facts.unknown
    assert facts.not_run("survive-length", "survive_component", "time_limit") == (
        f"attack survive-length not run: facts survive_component, time_limit unknown for task {user_module}:Counting")
    assert facts.not_run("reward-lattice", "public_env") is None  # decided for every task: not unknown
    assert residual_component(bare) == {"effort"} and reward_scale(bare) == 1000.0  # pp-hardened still hides one, bounds s
    f = tmp_path / "t.toml"
    f.write_text(textwrap.dedent(f"""
        name = "C"
        env = "{user_module}:Counting"
        [components]
        effort = "effort"
        extra = {{ info = "parts.a" }}
        [privacy]
        public_env = true
        residual_component = "extra"
        reward_scale = 7.5
        time_limit = 5
        survive_component = false
    """))
    declared = load_task(f)
    facts = facts_for(declared)
    assert facts.public_env and facts.time_limit == 5 and facts.survive_component is None
    assert "time_limit" not in facts.unknown and "survive_component" not in facts.unknown and "healthy_reward" not in facts.unknown
    assert residual_component(declared) == {"extra"} and reward_scale(declared) == 7.5
    assert task_from_json(declared.spec.model_dump(mode="json")).spec.privacy == declared.spec.privacy


def test_public_env_defaults() -> None:
    assert load_task("Pendulum-v1").spec.public_env() and get_task("Highway").spec.public_env()
    assert not load_task(ROBOT).spec.public_env()
    point = load_task(ROOT / "examples" / "own_robot" / "point_robot.toml")
    assert not point.spec.public_env() and not facts_for(point).public_env


def test_options_on_a_paper_tasks_env_id_give_a_task_of_that_env() -> None:
    """`--env CartPole-v1 --diagnostic x` used to be refused with "... or give its env id CartPole-v1"."""
    task = load_task("CartPole-v1", options=TaskOptions(max_episode_steps=50))
    assert task.name == "CartPole-v1" and task.spec.env.max_episode_steps == 50 and task is not get_task("CartPole")
    with pytest.raises(ConfigError, match="^CartPole is a paper task"):
        load_task("CartPole", options=TaskOptions(max_episode_steps=50))
