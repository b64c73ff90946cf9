"""Runs a linear policy on a task and turns the episodes into one raw feedback record.

This is client-side code: it sees raw parameters and raw returns. Nothing here may be imported
by ``ppprops.wire``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from .errors import ConfigError
from .policy import LinearPolicy, MLPPolicy, make_network
from .tasks.base import Task
from .values import Diagnostic, Feedback

if TYPE_CHECKING:  # the worker pool's modules load with the first pool (workers > 1), not with every study
    from concurrent.futures import ProcessPoolExecutor

# An env with no time limit whose episode runs this long is stopped with an error naming the fix
# (--max-episode-steps): a search must never hang on an episode that does not end.
SAFETY_STEPS = 100_000


class EpisodeLimitError(ConfigError):
    """An episode of an env without a time limit did not end within ``SAFETY_STEPS`` steps."""


class WorkerError(ConfigError):
    """A worker process could not make the task's env; the message is the worker's own error line."""


class EpisodeError(ConfigError):
    """The env raised in ``reset`` or ``step`` during an episode: one line naming the user's
    exception and where in their code (``tasks.envs.describe_user_error``); the run can be resumed
    once the env is fixed."""


class MalformedEnvError(EpisodeError):
    """The env returned a malformed value from ``reset`` or ``step`` (a wrong shape or type, a reward
    that is not a number: ``tasks.outputs``): one line naming the call, the episode seed and the
    value; the run can be resumed once the env is fixed."""


class PoolError(ConfigError):
    """The worker processes stopped (``BrokenProcessPool``); the line says the likely cause."""


POOL_BROKEN = ("the worker processes of workers > 1 stopped before running an episode (BrokenProcessPool). Most often a script "
               "that starts a search with workers > 1 is missing its guard: Python's multiprocessing re-imports the script in every "
               "worker, so put the code that runs the search under `if __name__ == \"__main__\":` (or use workers=1)")


class Fleet(Protocol):
    """What evaluates a round of trials side by side for ``Study.optimize``: ppprops's own
    ``Evaluator`` (its process pool), ``RayFleet`` (Ray tasks), or a user's fleet of rigs.

    ``evaluate_each(thetas, seeds_list)`` runs candidate i (raw parameters, shape (D,)) on one
    episode per seed of ``seeds_list[i]`` and returns, in the same order, its ``Feedback`` (raw
    values, the mean over its episodes: ``aggregate``) or the ``EpisodeError`` that stopped it.
    """

    def evaluate_each(self, thetas: Sequence[NDArray[np.floating]],
                      seeds_list: Sequence[Sequence[int]]) -> list[Feedback | EpisodeError]:
        """One Feedback (or the EpisodeError that stopped it) per candidate, in order."""
        ...


class Actor(Protocol):
    """Anything that maps a policy input (shape (n_s,)) to an env action: a ``LinearPolicy``, an SB3 model's wrapper."""

    def act(self, s: NDArray[np.float64]) -> Any:
        """The action for state ``s``."""
        ...


@dataclass(frozen=True)
class Episode:
    """One episode's raw outcome: return (reward units), each reward component's sum, and the reduced diagnostics."""

    ret: float
    components: dict[str, float]
    diagnostics: dict[str, Diagnostic]


def make_policy(task: Task, theta: NDArray[np.floating], env: Any) -> LinearPolicy | MLPPolicy:
    """The policy of ``theta`` (shape (D,)) for ``task`` in its family (``task.policy``: linear or MLP),
    with ``env``'s action bounds for continuous actions.

    Raises ConfigError when ``theta`` does not have ``task.D`` values.
    """
    space = env.action_space
    low = getattr(space, "low", None) if not task.discrete else None
    high = getattr(space, "high", None) if not task.discrete else None
    return make_network(theta, task.policy, task.n_s, task.n_a, discrete=task.discrete, low=low, high=high)


def step_cap(env: Any) -> int | None:
    """The safety cap for an env without a TimeLimit wrapper (None when one ends every episode)."""
    from .tasks.envs import has_time_limit

    return None if has_time_limit(env) else SAFETY_STEPS


def run_episode(task: Task, env: Any, policy: Actor, seed: int, *, max_steps: int | None = None,
                on_step: Callable[[NDArray[np.float64], Any], None] | None = None) -> Episode:  # fmt: skip
    """One episode of ``policy`` on ``env``, reset with ``seed``: the one episode loop of ppprops.

    What ``reset`` and every ``step`` return is checked against the env's declared spaces
    (``tasks.outputs.OutputCheck``: Gymnasium's passive checks) before it is used. A non-finite
    observation or reward ends the episode and is marked (diagnostic ``numerical_fault``), never
    propagated. ``max_steps`` (see ``step_cap``) bounds an episode of an env with no time limit:
    past it the episode is an ``EpisodeLimitError``, never an endless loop. ``on_step(state,
    action)`` sees each policy input (the task's observation vector, shape (n_s,)) and the action
    taken, before the step (R2PO's rollout evidence).

    Raises:
        EpisodeError: the env raised in ``reset`` or ``step``.
        MalformedEnvError: the env returned a malformed value (the call, the seed and the value, in one line).
        EpisodeLimitError: the episode ran past ``max_steps``.
        FeedbackKeyError: the env's info lacks a declared component or diagnostic.
    """
    from .tasks.outputs import OutputCheck, call_line

    recorder = task.feedback()
    check = OutputCheck(env, getattr(task.observation, "keys", None))
    try:
        result = env.reset(seed=seed)
    except Exception as e:  # the user's env: one line, never a traceback
        raise EpisodeError(f"the env of task {task.name} raised in reset (episode seed {seed}): {_user_error(e)}") from None
    problem = check.reset(result)
    if problem is not None:
        raise MalformedEnvError(call_line(task.name, "reset", seed, problem))
    obs, info = result
    total = 0.0
    steps = 0
    terminated = truncated = False
    numerical_fault = False
    s = task.observation(obs)
    while True:
        if not np.all(np.isfinite(s)):
            numerical_fault = True
            break
        action = policy.act(s)
        if on_step is not None:
            on_step(s, action)
        try:
            result = env.step(action)
        except Exception as e:
            raise EpisodeError(f"the env of task {task.name} raised in step {steps + 1} (episode seed {seed}): "
                               f"{_user_error(e)}") from None
        problem = check.step(result)
        if problem is not None:
            raise MalformedEnvError(call_line(task.name, f"step {steps + 1}", seed, problem))
        obs, reward, terminated, truncated, info = result
        reward = float(reward)
        if not np.isfinite(reward) or not np.isfinite(total + reward):
            numerical_fault = True  # a bad reward, or a sum that overflowed
            break
        steps += 1
        total += reward
        s = task.observation(obs)
        if not np.all(np.isfinite(s)):
            numerical_fault = True  # recorders derive diagnostics from the observation: keep it out
            break
        recorder.step(obs, reward, info)
        if terminated or truncated:
            break
        if max_steps is not None and steps >= max_steps:
            raise EpisodeLimitError(f"an episode of {task.env_id} ran {steps} steps without ending and the env has no time "
                                    "limit: give one with --max-episode-steps N (max_episode_steps in a task file)")  # fmt: skip
    fb = recorder.finish(terminated=bool(terminated), truncated=bool(truncated), steps=steps, info=info)
    diagnostics = dict(fb.diagnostics)
    if numerical_fault:
        diagnostics["numerical_fault"] = 1.0
    return Episode(ret=total, components=dict(fb.components), diagnostics=diagnostics)


def exit_if_importing_main_in_a_worker() -> None:
    """In a worker process that multiprocessing started, while it re-imports the user's main script
    (an unguarded script that starts a search with workers > 1): leave quietly, before anything is
    made or written. The parent then sees its pool break and says, in one line, to add the
    ``if __name__ == "__main__":`` guard (``POOL_BROKEN``); no second run starts, no traceback
    comes from the worker."""
    import sys
    from types import FrameType

    frame: FrameType | None = sys._getframe(1)
    while frame is not None:  # module-level code of the script multiprocessing re-imports as __mp_main__
        if frame.f_code.co_name == "<module>" and frame.f_globals.get("__name__") == "__mp_main__":
            raise SystemExit(3)
        frame = frame.f_back


def _user_error(e: BaseException) -> str:
    from .tasks.envs import describe_user_error

    return describe_user_error(e)


def aggregate(episodes: Sequence[Episode]) -> Feedback:
    """Mean of returns and components; numeric diagnostics averaged, categorical ones counted."""
    n = len(episodes)
    ret = float(np.mean([e.ret for e in episodes]))
    comp_keys = list(dict.fromkeys(k for e in episodes for k in e.components))
    components = {k: float(np.mean([e.components.get(k, 0.0) for e in episodes])) for k in comp_keys}
    diag_keys = list(dict.fromkeys(k for e in episodes for k in e.diagnostics))
    diagnostics: dict[str, Diagnostic] = {}
    for k in diag_keys:
        values = [e.diagnostics.get(k) for e in episodes]
        if all(isinstance(v, float) for v in values):
            diagnostics[k] = float(np.mean(values))  # type: ignore[arg-type]
        elif n == 1:
            diagnostics[k] = str(values[0])
        else:
            counts = Counter(str(v) for v in values)
            diagnostics[k] = ", ".join(f"{name} x{c}" for name, c in counts.most_common())
    return Feedback(ret=ret, components=components, diagnostics=diagnostics, episode_returns=tuple(e.ret for e in episodes))


# Worker-process state: one task and one env per worker, made once and reused across episodes.
_worker: dict[str, Any] = {}


def _init_worker(ref: Any) -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group: the parent decides
    # A failure here would kill the pool with a traceback; keep it, and report it as one line instead.
    try:
        from .tasks import resolve_task

        task = resolve_task(ref)
        _worker["task"] = task
        _worker["env"] = task.make_env()
        _worker["cap"] = step_cap(_worker["env"])
    except Exception as e:
        _worker["error"] = f"a worker process cannot make the env of task {getattr(ref, 'name', None) or _ref_name(ref)}: {e}"


def _ref_name(ref: Any) -> str:
    return str(ref.get("name")) if isinstance(ref, dict) else str(ref)


def _worker_episode(theta: NDArray[np.floating], seed: int) -> Episode:
    if "error" in _worker:
        raise WorkerError(_worker["error"])
    task, env = _worker["task"], _worker["env"]
    return run_episode(task, env, make_policy(task, theta, env), seed, max_steps=_worker["cap"])


def _start_method() -> str:
    # Never fork: the parent may run threads (the embedded LLM server), and a forked child can
    # inherit their locks held. forkserver forks from a clean single-threaded server instead.
    import multiprocessing

    return "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def check_parallel(task: Task) -> None:
    """Refuse, in one line, a task whose env worker processes cannot make (see ``EnvRecipe.local_only``)."""
    local = task.spec.env.local_only() if task.spec is not None else None
    if local is not None:
        raise ConfigError(f"task {task.name} cannot run in worker processes: {local} (or use workers=1)")


class Evaluator:
    """Runs candidates' episodes, serially in one kept-alive env or in a pool of worker processes.

    ``env``: an env of ``task`` made already, which the evaluator uses as its own (and closes)
    instead of making one. With ``workers=N > 1`` every episode is a separate job for a pool of N
    processes, each holding its own env. An episode depends only on (task, theta, seed), since ``env.reset(seed=...)``
    reseeds the env, so the results are bit-identical to a serial run, in the same order.
    """

    def __init__(self, task: Task, workers: int = 1, *, env: Any = None) -> None:
        if workers < 1:
            raise ConfigError(f"workers must be at least 1, got {workers}")
        self.task = task
        self.workers = workers
        self._env: Any = env  # an env of the task made already (``runner.check_startable``): adopted, closed by ``close``
        self._cap: int | None = None if env is None else step_cap(env)
        self._pool: ProcessPoolExecutor | None = None

    @property
    def env(self) -> Any:
        """The evaluator's own env (made on first use), for rollouts outside ``evaluate``."""
        if self._env is None:
            self._env = self.task.make_env()
            self._cap = step_cap(self._env)
        return self._env

    def _episodes_serial(
        self, thetas: Sequence[NDArray[np.floating]], seeds_list: Sequence[Sequence[int]]
    ) -> list[list[Episode]]:
        out = []
        for theta, seeds in zip(thetas, seeds_list, strict=True):
            policy = make_policy(self.task, theta, self.env)
            out.append([run_episode(self.task, self.env, policy, s, max_steps=self._cap) for s in seeds])
        return out

    def _pool_for(self) -> ProcessPoolExecutor:
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            from .tasks import task_ref

            if self.task.setup is not None:
                self.task.setup()  # a missing extra fails here, with its own message, not in a worker
            check_parallel(self.task)
            ctx = multiprocessing.get_context(_start_method())
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=ctx, initializer=_init_worker, initargs=(task_ref(self.task),)
            )
        return self._pool

    def _episodes_parallel(
        self, thetas: Sequence[NDArray[np.floating]], seeds_list: Sequence[Sequence[int]]
    ) -> list[list[Episode]]:
        from concurrent.futures.process import BrokenProcessPool

        pool = self._pool_for()
        jobs = [
            (np.asarray(theta, dtype=np.float64), int(s)) for theta, seeds in zip(thetas, seeds_list, strict=True) for s in seeds
        ]
        chunk = max(1, len(jobs) // (4 * self.workers))  # fewer round trips for many short episodes
        try:
            flat = list(pool.map(_worker_episode, [j[0] for j in jobs], [j[1] for j in jobs], chunksize=chunk))
        except BrokenProcessPool:
            self._pool = None  # gone; a later evaluate starts a new one
            raise PoolError(POOL_BROKEN) from None
        out, start = [], 0
        for seeds in seeds_list:
            out.append(flat[start : start + len(seeds)])
            start += len(seeds)
        return out

    def evaluate(self, theta: NDArray[np.floating], seeds: Sequence[int]) -> Feedback:
        """Raw feedback of ``theta`` (shape (D,)) averaged over one episode per seed in ``seeds`` (paper Sec. II-C)."""
        return self.evaluate_many([theta], [seeds])[0]

    def evaluate_many(self, thetas: Sequence[NDArray[np.floating]], seeds_list: Sequence[Sequence[int]]) -> list[Feedback]:
        """One Feedback per theta, theta i run on the seeds ``seeds_list[i]``; a batch fills the pool better."""
        if len(thetas) != len(seeds_list):
            raise ConfigError(f"{len(thetas)} parameter vectors but {len(seeds_list)} seed lists")
        run = self._episodes_serial if self.workers == 1 else self._episodes_parallel
        return [aggregate(eps) for eps in run(thetas, seeds_list)]

    def evaluate_each(self, thetas: Sequence[NDArray[np.floating]],
                      seeds_list: Sequence[Sequence[int]]) -> list[Feedback | EpisodeError]:
        """Like ``evaluate_many`` (the ``Fleet`` protocol), but a candidate whose env raised in an
        episode (``EpisodeError``) gets the error in its place while the others are evaluated:
        ``--on-episode-error fail-trial`` records it as a failed trial. Other errors (a broken
        pool, an env that breaks its task's declaration) are raised."""
        if len(thetas) != len(seeds_list):
            raise ConfigError(f"{len(thetas)} parameter vectors but {len(seeds_list)} seed lists")
        if self.workers == 1:
            out: list[Feedback | EpisodeError] = []
            for theta, seeds in zip(thetas, seeds_list, strict=True):
                try:
                    out.append(aggregate(self._episodes_serial([theta], [seeds])[0]))
                except EpisodeError as e:
                    out.append(e)
            return out
        from concurrent.futures.process import BrokenProcessPool

        pool = self._pool_for()
        try:
            futures = [[pool.submit(_worker_episode, np.asarray(theta, dtype=np.float64), int(s)) for s in seeds]
                       for theta, seeds in zip(thetas, seeds_list, strict=True)]
            results: list[Feedback | EpisodeError] = []
            for fs in futures:
                try:
                    results.append(aggregate([f.result() for f in fs]))
                except EpisodeError as e:
                    results.append(e)
            return results
        except BrokenProcessPool:
            self._pool = None
            raise PoolError(POOL_BROKEN) from None

    def close(self) -> None:
        """Shut the worker pool down (if any); the evaluator can still be used serially afterwards."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._env is not None:
            self._env.close()
            self._env = None

    def __enter__(self) -> Evaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
