"""Standard RL baselines (paper, "Standard RL Baselines"): Stable-Baselines3 agents with default settings.

An agent (``MlpPolicy``, the library's default hyperparameters) trains for a fixed number of
timesteps on exactly what a PP-ProPS policy observes, the task's observation adapter output (so
``Ant-Ultra`` trains on the 10 Ultra variables), and is then scored with deterministic actions on
the same fresh episode seeds as a PP-ProPS run's final evaluation, by the same episode runner. The
result is a run directory like a search's: ``run.sqlite`` (config, training episodes, final
evaluation) and the trained ``model.zip``; ``ppprops show`` reads it.

SAC, TD3 and DDPG take continuous actions only and DQN discrete ones only, as in the paper, whose
table marks the other combinations "--"; asking for one is a ConfigError. torch and
Stable-Baselines3 (the ``rl`` extra) are imported only once the settings have been checked.
"""

from __future__ import annotations

import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from .. import seeding
from ..errors import ConfigError, MissingExtraError
from ..evaluation import run_episode
from ..methods import rl_algos, rl_method
from ..status import RunKind, RunStatus
from ..store import DB_NAME, open_store
from ..tasks import Task, get_task
from ..values import FinalEval
from .algorithms import Algorithm
from .record import KIND, MODEL_NAME, NO_CANDIDATE, TrainingLog

if TYPE_CHECKING:
    from stable_baselines3.common.base_class import BaseAlgorithm

POLICY = "MlpPolicy"
DEVICES = ("cpu", "cuda", "auto")


@dataclass(frozen=True)
class RLConfig:
    """Settings of one RL baseline run; stored (with ``kind`` and the library defaults) as its config."""

    task: str
    algo: str
    timesteps: int
    seed: int = 0
    final_episodes: int = 20
    # Small MLPs train faster on CPU than on a GPU (SB3 warns about PPO on GPU), and CPU runs repeat.
    device: str = "cpu"
    # torch CPU threads. 64x64 MLPs gain nothing from more, and spinning threads lose a lot on a busy machine.
    threads: int = 1

    @property
    def method(self) -> str:
        """The registry name the run is stored under: ``rl-<algo>``."""
        return rl_method(self.algo).name

    def validate(self) -> None:
        """Check every setting before anything is built (CLI flag names in the messages).

        Raises:
            ConfigError: an unknown ``algo`` or ``device``, ``timesteps`` < 1, ``final_episodes`` < 0,
                ``threads`` < 1, or a ``seed`` outside [0, 2^32).
        """
        checks = [
            (self.algo in rl_algos(), f"--algo must be one of {', '.join(rl_algos())}, got {self.algo!r}"),
            (self.timesteps >= 1, f"--timesteps must be >= 1, got {self.timesteps}"),
            (self.final_episodes >= 0, f"--final-episodes must be >= 0, got {self.final_episodes}"),
            (0 <= self.seed < 2**32, f"--seed must be in [0, 2^32) (Stable-Baselines3 seeds numpy with it), got {self.seed}"),
            (self.device in DEVICES, f"--device must be one of {', '.join(DEVICES)}, got {self.device!r}"),
            (self.threads >= 1, f"--threads must be >= 1, got {self.threads}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)


def check_applicable(algo: Algorithm, task: Task) -> None:
    """SAC/TD3/DDPG need continuous actions, DQN discrete ones (the paper's "--" cells)."""
    if not algo.applies_to(task.action_type):
        needs = " or ".join(sorted(algo.action_types))
        raise ConfigError(
            f"{algo.name} ({algo.title}) takes {needs} actions only; {task.name} has {task.action_type} actions (the paper marks this combination '--')"
        )


class TaskObservation(gym.ObservationWrapper):  # type: ignore[type-arg]
    """Shows the agent the task's state vector s (``task.observation``), as float32 of length n_s."""

    def __init__(self, env: gym.Env, task: Task) -> None:  # type: ignore[type-arg]
        super().__init__(env)
        self.task = task
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(task.n_s,), dtype=np.float32)

    def observation(self, observation: Any) -> NDArray[np.float32]:
        """The task's state vector s of the env's raw ``observation``, float32, shape (n_s,)."""
        return np.asarray(self.task.observation(observation), dtype=np.float32)


def make_env(task: Task) -> TaskObservation:
    """A new env of ``task`` whose observations are the policy input s (shape (n_s,), float32).

    Raises what ``task.make_env`` raises (a MissingExtraError for a simulator extra not installed).
    """
    return TaskObservation(task.make_env(), task)


def _sb3() -> Any:
    try:
        from . import sb3
    except ImportError as e:
        raise MissingExtraError("rl", "ppprops baseline rl") from e
    return sb3


def evaluate_model(model: BaseAlgorithm, task: Task, seeds: list[int]) -> tuple[float, ...]:
    """Deterministic returns of ``model`` on ``seeds``, through PP-ProPS's episode runner.

    One episode per seed on one env of ``task``; ``returns[i]`` (raw reward units) is the episode
    reset with ``seeds[i]``, so the numbers compare with a search's final evaluation on the same seeds.

    Raises:
        MissingExtraError: the ``rl`` extra is not installed.
        EpisodeLimitError, FeedbackKeyError: as ``ppprops.evaluation.run_episode``.
    """
    policy = _sb3().ModelPolicy(model, task.discrete)
    env = task.make_env()
    try:
        return tuple(run_episode(task, env, policy, s).ret for s in seeds)  # duck-typed: it needs only act(s)
    finally:
        env.close()


def load_model(run_dir: Path) -> BaseAlgorithm:
    """The trained model (``model.zip``) of an RL run directory, loaded on CPU.

    Raises:
        StoreError: ``run_dir`` is not a run directory.
        ConfigError: the run is not an RL baseline run.
        MissingExtraError: the ``rl`` extra is not installed.
    """
    with open_store(run_dir) as store:
        config = store.config()
    if RunKind.of_config(config) is not RunKind.RL:
        raise ConfigError(f"{run_dir} is not an RL baseline run")
    cls = _sb3().algorithm_class(rl_method(config["algo"]).algorithm)
    return cls.load(Path(run_dir) / MODEL_NAME, device="cpu")


def default_run_dir(config: RLConfig) -> Path:
    """``runs/<task>__rl-<algo>__<seed>__<YYYYmmdd-HHMMSS>`` (local time), relative to the working directory.

    Raises:
        UnknownTaskError, ConfigError: as ``ppprops.tasks.get_task`` for ``config.task``.
    """
    task = get_task(config.task)
    return Path("runs") / f"{task.name}__{config.method}__{config.seed}__{time.strftime('%Y%m%d-%H%M%S')}"


def _claim_dir(run_dir: Path) -> None:
    if run_dir.exists() and any(run_dir.iterdir()):
        what = "another run" if (run_dir / DB_NAME).exists() else "files"
        raise ConfigError(f"output directory {run_dir} already holds {what}; choose a new --out")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot create output directory {run_dir}: {e.strerror}") from None


def run_baseline(config: RLConfig, run_dir: Path, *, progress: bool = False) -> FinalEval | None:
    """Train, save ``model.zip``, run the final evaluation; everything recorded in ``run_dir``.

    The paper's standard RL baselines (Sec. IV-E, Table tab:baselines): ``config.algo`` with SB3's
    default hyperparameters trains for ``config.timesteps`` agent steps on the task's state vector,
    then runs ``config.final_episodes`` deterministic episodes on ``final_eval_seeds(seed, n)``.
    The run's status ends ``finished``, or ``interrupted`` when training or evaluation is stopped
    (Ctrl-C) or fails; ``progress`` shows a bar of timesteps on stderr.

    Returns:
        The final evaluation (its ``returns`` in raw reward units), or None with ``final_episodes=0``.

    Raises:
        ConfigError: bad settings, an algorithm that does not take the task's action type, an
            output directory that already holds files or cannot be created.
        UnknownTaskError: ``config.task`` names no task.
        MissingExtraError: the ``rl`` extra (or the task's simulator extra) is not installed.
    """
    config.validate()
    task = get_task(config.task)
    algo = rl_method(config.algo).algorithm
    check_applicable(algo, task)
    sb3 = _sb3()
    cls = sb3.algorithm_class(algo)
    sb3.set_threads(config.threads)
    run_dir = Path(run_dir)
    env = sb3.Monitor(make_env(task))  # makes the env first: a missing simulator extra fails before the directory
    try:
        _claim_dir(run_dir)
        stored = {**asdict(config), "task": task.name, "kind": KIND, "method": config.method, "policy": POLICY,
                  "hyperparameters": sb3.default_hyperparameters(cls), "versions": sb3.versions()}  # fmt: skip
        with open_store(run_dir, create=True) as store, TrainingLog(store.path) as log:
            store.init_run(f"{task.name}__{config.method}__{config.seed}__{uuid.uuid4().hex[:8]}", stored, "")
            try:
                model = cls(POLICY, env, seed=config.seed, device=config.device, verbose=0)
                sb3.silence_logger(model)
                logger = sb3.EpisodeLogger(log, total=config.timesteps, label=f"{task.name} {config.method}", progress=progress)
                t0 = time.perf_counter()
                model.learn(total_timesteps=config.timesteps, callback=logger)
                log.set_info(timesteps_done=int(model.num_timesteps), wall_s=time.perf_counter() - t0)
                model.save(run_dir / MODEL_NAME)
                seeds = seeding.final_eval_seeds(config.seed, config.final_episodes)
                fe = None
                if seeds:
                    fe = FinalEval(candidate_index=NO_CANDIDATE, returns=evaluate_model(model, task, seeds), seeds=tuple(seeds))
                    store.set_final_eval(fe)
                store.set_status(RunStatus.FINISHED)
                return fe
            except BaseException:  # Ctrl-C or a crash: show must not call the run "running" forever
                store.set_status(RunStatus.INTERRUPTED)
                raise
    finally:
        env.close()
