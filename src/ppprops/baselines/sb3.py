"""Everything that touches Stable-Baselines3 and torch; imported only when an RL baseline trains.

``ppprops.baselines.rl`` imports this module inside a try block, so a missing ``rl`` extra becomes
one line naming it rather than a traceback.
"""

from __future__ import annotations

import importlib
import inspect
import time
from typing import Any

import numpy as np
import stable_baselines3
import torch
from numpy.typing import NDArray
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.monitor import Monitor
from tqdm import tqdm

from ..errors import MissingExtraError
from .algorithms import Algorithm
from .record import TrainingEpisode, TrainingLog

__all__ = ["Monitor", "EpisodeLogger", "ModelPolicy", "algorithm_class", "default_hyperparameters", "set_threads", "versions"]

# Constructor arguments that are wiring or logging, not hyperparameters.
_NOT_HYPERPARAMETERS = {"self", "policy", "env", "verbose", "seed", "device", "_init_setup_model", "tensorboard_log",
                        "stats_window_size"}  # fmt: skip


def algorithm_class(algo: Algorithm) -> type[BaseAlgorithm]:
    """The Stable-Baselines3 (or sb3-contrib) class of ``algo``, e.g. ``stable_baselines3.PPO``.

    Raises:
        MissingExtraError: the module is not installed (sb3-contrib is part of the ``rl`` extra).
    """
    try:
        module = importlib.import_module(algo.module)
    except ImportError as e:  # sb3-contrib (TRPO) is part of the same extra
        raise MissingExtraError("rl", "ppprops baseline rl") from e
    cls: type[BaseAlgorithm] = getattr(module, algo.cls)
    return cls


def _jsonable(v: Any) -> bool:
    if v is None or isinstance(v, (bool, int, float, str)):
        return True
    return isinstance(v, (tuple, list)) and all(_jsonable(x) for x in v)


def default_hyperparameters(cls: type[BaseAlgorithm]) -> dict[str, Any]:
    """The library's own defaults for ``cls``, read from its signature, so the run records what it used."""
    out: dict[str, Any] = {}
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name in _NOT_HYPERPARAMETERS or p.default is inspect.Parameter.empty:
            continue
        out[name] = list(p.default) if isinstance(p.default, tuple) else p.default if _jsonable(p.default) else repr(p.default)
    return out


def set_threads(n: int) -> None:
    """torch's intra-op CPU threads for this process (training and evaluation)."""
    torch.set_num_threads(n)


def silence_logger(model: BaseAlgorithm) -> None:
    """Give ``model`` a logger with no outputs: the run's store keeps the training episodes, and SB3's
    default logger would otherwise create an empty ``SB3-<date>`` folder in the temp directory on
    every ``learn``."""
    model.set_logger(Logger(folder=None, output_formats=[]))


def versions() -> dict[str, str]:
    """Installed versions of stable_baselines3, torch and (when installed) sb3_contrib, for the run record."""
    out = {"stable_baselines3": stable_baselines3.__version__, "torch": torch.__version__}
    try:
        import sb3_contrib

        out["sb3_contrib"] = sb3_contrib.__version__
    except ImportError:
        pass
    return out


class EpisodeLogger(BaseCallback):
    """Writes every finished training episode (Monitor's ``info["episode"]``) to the run's store.

    Episodes are buffered and written at the end of a rollout at most every ``flush_s`` seconds, and
    at the end of training, so an interrupted run keeps what it had seen up to a few seconds before.
    """

    def __init__(self, log: TrainingLog, *, total: int, label: str, progress: bool, flush_s: float = 2.0) -> None:
        super().__init__(verbose=0)
        self.log = log
        self.total = total
        self.label = label
        self.progress = progress
        self.flush_s = flush_s
        self._pending: list[TrainingEpisode] = []
        self._count = 0
        self._last_flush = time.monotonic()
        self._bar: Any = None

    def _on_training_start(self) -> None:
        self._bar = tqdm(total=self.total, desc=self.label, unit="step", disable=not self.progress, leave=False)

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", ()):
            ep = info.get("episode")
            if ep is not None:
                self._pending.append(TrainingEpisode(self._count, int(self.num_timesteps), float(ep["r"]), int(ep["l"])))
                self._count += 1
                self._bar.set_postfix_str(f"last return {float(ep['r']):.1f}", refresh=False)
        self._bar.update(self.num_timesteps - self._bar.n)
        return True

    def _on_rollout_end(self) -> None:
        if time.monotonic() - self._last_flush >= self.flush_s:
            self._flush()

    def _on_training_end(self) -> None:
        self._flush()
        self._bar.close()

    def _flush(self) -> None:
        self.log.add_episodes(self._pending)
        self._pending = []
        self._last_flush = time.monotonic()


class ModelPolicy:
    """Lets PP-ProPS's own episode runner drive a trained model: ``act(s)`` is its deterministic action.

    The runner applies the task's observation adapter first, so ``s`` is what the agent saw in training.
    """

    def __init__(self, model: BaseAlgorithm, discrete: bool) -> None:
        self.model = model
        self.discrete = discrete

    def act(self, s: NDArray[np.floating]) -> int | NDArray[np.floating]:
        """The model's deterministic action for state ``s`` (shape (n_s,)): an int for discrete
        actions, else an array of shape (n_a,) in the env's action units."""
        action, _ = self.model.predict(np.asarray(s, dtype=np.float32), deterministic=True)
        return int(action) if self.discrete else np.asarray(action)
