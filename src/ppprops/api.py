"""The Python API: one call runs a search and returns its result; the same objects come back from a
resumed run, a stored run and a policy evaluation.

    import ppprops

    result = ppprops.search("CartPole", method="pp", warmup=10, iterations=50, final_episodes=20, seed=0, out="runs/x")
    result.final.mean, result.policy.W        # final-evaluation mean return; W of shape (n_s, n_a)
    action = result.policy(obs)               # the deployable policy on a raw env observation

``search`` takes a task in every form ``ppprops run`` does, and more: a paper task name, a
Gymnasium id, ``module:EnvId`` or ``module:attr``, a task file path, an env factory (a class or a
function returning a Gymnasium env), or a ``TaskSpec`` / ``Task``. Keyword names are those of the
``ppprops run`` flags (``--final-episodes`` is ``final_episodes``). Any method; any LLM, by endpoint
settings (``base_url``, ``model``, ...) or as a ``chat`` object (``ppprops.runner.ChatModel``).

Errors are ``ppprops.errors.PPPropsError`` subclasses with a one-line message (``ConfigError`` for
bad input, ``LLMError`` when the endpoint stays down, ``StoreError`` for run directories);
nothing here prints unless ``progress=True``.
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .config import RunConfig
from .errors import ConfigError
from .policy_file import Policy, load_policy
from .status import RunKind
from .values import Candidate

Pathish = str | os.PathLike[str]
TaskLike = Any  # str | os.PathLike | Callable[..., gymnasium.Env] | TaskSpec | Task (see ppprops.tasks.load_task)
POLICY_NAME = "best_policy.json"


@dataclass(frozen=True)
class Evaluation:
    """Returns of fresh episodes of one policy: ``returns[i]`` is the episode with seed ``seeds[i]``."""

    task: str
    returns: tuple[float, ...]
    seeds: tuple[int, ...]
    seed: int  # the evaluation seed the episode seeds derive from (ppprops.seeding.final_eval_seeds)

    @property
    def mean(self) -> float:
        """Mean episode return (raw reward units); NaN with no episodes."""
        return float(np.mean(self.returns)) if self.returns else float("nan")

    @property
    def std(self) -> float:
        """Population standard deviation of the episode returns (numpy's default); NaN with no episodes."""
        return float(np.std(self.returns)) if self.returns else float("nan")


@dataclass(frozen=True, repr=False)
class SearchResult:
    """A run: where it is, how it ended, its best policy and every candidate it evaluated.

    ``history[i]`` is candidate i (raw parameters ``params`` of shape (D,), its ``feedback``, its
    encoded form as the LLM saw it, and its ``source``: warmup, llm, fallback, ...). ``best_return``
    is the best candidate's search-time mean return; ``final`` the final evaluation of it on fresh
    episodes (None with ``final_episodes=0``). ``policy`` is the deployable policy file
    (``run_dir / "best_policy.json"``) as a callable; None until the run has finished.
    """

    run_dir: Path
    task: str
    method: str
    status: str
    config: RunConfig
    history: tuple[Candidate, ...]
    best_index: int | None
    best_return: float | None
    final: Evaluation | None
    policy: Policy | None

    @property
    def theta(self) -> NDArray[np.float64] | None:
        """The decoded best parameters, shape (D,) with D = (n_s + 1) * n_a (layout: ppprops.policy)."""
        return None if self.policy is None else self.policy.theta

    @property
    def W(self) -> NDArray[np.float64] | None:
        """Weights of u = s @ W + b (paper Eq. 10: u = W^T s + b), shape (n_s, n_a)."""
        return None if self.policy is None else self.policy.W

    @property
    def b(self) -> NDArray[np.float64] | None:
        """Bias of u = s @ W + b, shape (n_a,)."""
        return None if self.policy is None else self.policy.b

    def __repr__(self) -> str:
        """One line: the run, its outcome and the history's length (not every candidate)."""
        final = "None" if self.final is None else f"{self.final.mean:.2f} over {len(self.final.returns)} episodes"
        return (f"SearchResult(run_dir={str(self.run_dir)!r}, task={self.task!r}, method={self.method!r}, status={self.status!r}, "
                f"history=<{len(self.history)} candidates>, best_index={self.best_index}, best_return={self.best_return}, "
                f"final={final})")


def _default_out(task: str, method: str, seed: int) -> Path:
    safe = re.sub(r"[^A-Za-z0-9_.+-]", "_", task)
    return Path("runs") / f"{safe}__{method}__{seed}__{time.strftime('%Y%m%d-%H%M%S')}"


def search(
    task: TaskLike,
    *,
    method: str = "pp",
    warmup: int = 10,
    iterations: int = 50,
    top_k: int = 10,
    episodes: int | None = None,
    final_episodes: int = 20,
    seed: int = 0,
    out: Pathish | None = None,
    box: tuple[float, float] = (-6.0, 6.0),
    decimals: int = 2,
    workers: int = 1,
    env_kwargs: Mapping[str, Any] | None = None,
    max_episode_steps: int | None = None,
    gym_packages: Sequence[str] = (),
    obs_keys: Sequence[str] | None = None,
    components: Sequence[str] = (),
    diagnostics: Sequence[str] = (),
    encode_params: bool | None = None,
    scale_rewards: bool | None = None,
    detailed_feedback: bool | None = None,
    disclose_optimum: bool | None = None,
    disclose_reward_structure: bool | None = None,
    secret_offsets: bool | None = None,
    warp_params: bool | None = None,
    warp_rewards: bool | None = None,
    hide_return_diagnostics: bool | None = None,
    encoded_warmup: bool | None = None,
    describe_task: bool | None = None,
    prompt_params: str = "list",
    param_digits: int | None = None,
    prompt_layout: str = "static-first",
    prompt_form: str = "auto",
    parse_retries: int = 2,
    on_llm_failure: str = "stop",
    base_url: str | None = None,
    model: str | None = None,
    api_key_env: str | None = None,
    temperature: float | None = None,
    max_tokens: int | None = None,
    timeout: float = 300.0,
    reasoning_effort: str | None = None,
    structured: str = "auto",
    context_size: int = 16384,
    retries: int = 4,
    chat: Any = None,
    progress: bool = False,
) -> SearchResult:
    """Run a policy search (paper Sec. II-E, Algorithm 1; settings of Sec. III) on ``task`` and return its result.

    Args:
        task: a paper task name (``"Ant-Ultra"``), a Gymnasium id, ``"module:EnvId"`` or
            ``"module:attr"``, a task file path (``.toml``), an env factory (an ``Env`` class or a
            function returning an env, called with ``env_kwargs``), a ``TaskSpec`` or a ``Task``.
            A factory with no importable name (a lambda, a local function) works in this process
            only; one defined at the top level of a module (or of the script being run) also works
            with ``workers > 1``, ``resume`` and ``policy eval`` from a fresh process.
        method: a search method of the registry (``ppprops.methods``): ``vanilla``, ``pe``, ``df``,
            ``pp`` (default), ``pp-hardened``, ``r2po``, ``random`` or ``cmaes``.
        warmup: random warm-up policies (``--warmup``).
        iterations: LLM proposals (r2po: LLM calls; random, cmaes: samples) after the warm-up.
        top_k: history entries in the prompt, best last (Eq. 9, Sec. II-D); 0 keeps every entry.
        episodes: episodes per candidate (default: the method's, 1; 20 for r2po).
        final_episodes: fresh episodes for the best policy at the end.
        seed: the run seed (episode seeds, warm-up, fallbacks; never the secrets).
        out: the run directory (default ``runs/<task>__<method>__<seed>__<time>``); it must not
            hold anything yet.
        box: (low, high), the feasible range of every raw parameter.
        decimals: decimals of the numbers in the prompt.
        workers: processes that run episodes in parallel (results identical to one).
        env_kwargs: keyword arguments of the env's constructor (win over a task file's).
        max_episode_steps: time limit of an episode (needed when the env has none).
        gym_packages: modules to import before the env is made (e.g. one that registers it).
        obs_keys: for a Dict observation, the entries the policy sees, in this order.
        components: info keys summed over an episode as reward components.
        diagnostics: info keys reported as diagnostics (last value of an episode).
        encode_params: switch Eq. 5 (theta~ = A theta) on or off; None keeps the preset's.
        scale_rewards: switch Eq. 7-8 (r~ = c r, for the return and each component) on or off; None keeps the preset's.
        detailed_feedback: switch component and diagnostic feedback (Sec. II-C); None keeps the preset's.
        disclose_optimum: state the optimal return (Vanilla ProPS); None keeps the preset's.
        disclose_reward_structure: state the numeric reward definition; None keeps the preset's.
        secret_offsets: hardening switch (docs/threat-model.md); None keeps the preset's.
        warp_params: hardening switch (docs/threat-model.md); None keeps the preset's.
        warp_rewards: hardening switch (docs/threat-model.md); None keeps the preset's.
        hide_return_diagnostics: hardening switch (docs/threat-model.md); None keeps the preset's.
        encoded_warmup: hardening switch (docs/threat-model.md); None keeps the preset's.
        describe_task: the task description in the prompt (ProPS+ on, ProPS off); None keeps on.
        prompt_params: history parameters as one ``list`` or ProPS ``indexed`` pairs.
        param_digits: significant digits of each listed parameter (0: fixed decimals; None: the
            form's default, 3 in the chat form, 2 in the document form).
        prompt_layout: ``static-first`` (fixed sections first) or ``history-first``.
        prompt_form: ``auto`` (the document form for the embedded model, the paper's chat prompt
            otherwise), ``chat`` or ``document`` (a completions-endpoint document the model continues).
        parse_retries: corrections asked for before a fallback candidate.
        on_llm_failure: ``stop`` (resumable) or ``skip`` (fallback candidate) when the endpoint stays down.
        base_url: OpenAI-compatible API root (default: the embedded model).
        model: the model name at ``base_url``.
        api_key_env: the environment variable holding the API key (never stored).
        temperature: sampling temperature, 0 to 2 (None: 1.0 for the chat form; the document form
            alternates 0.6 and 1.0).
        max_tokens: answer budget in tokens (default: room for D numbers, and for reasoning).
        timeout: seconds per request.
        reasoning_effort: ``none``, ``minimal``, ``low``, ``medium`` or ``high`` (reasoning models).
        structured: ``auto``, ``json_schema``, ``grammar`` or ``none``.
        context_size: the embedded model's context window, in tokens.
        retries: retries of one request after a transient fault.
        chat: instead of an endpoint, any object with ``complete(messages, *, D, seed)`` returning
            a ``ppprops.llm.client.Exchange``, ``count_tokens(text)`` and ``close()``; the caller
            keeps it (it is not closed). Its exchanges are recorded like an endpoint's. With
            ``complete_document(prompt, *, D, seed, grammar)`` too it gets the document form under
            ``prompt_form="auto"``; without, the chat form.
        progress: show a progress bar on stderr.

    Returns:
        The finished run (``SearchResult``).

    Raises:
        ConfigError: bad settings or task (one line: unknown id, a module that fails to import and
            why, an info key missing from the env's info or not a scalar, an occupied ``out``).
        LLMError: the endpoint stayed down past the retry bound (the run is saved: ``resume`` it).
        StoreError: the run directory cannot be written.
        MissingExtraError: the task needs an extra that is not installed (``mujoco``, ``robotics``, ...).
    """
    from .methods import get_method
    from .settings import build_config
    from .tasks import load_task

    switches = dict(encode_params=encode_params, scale_rewards=scale_rewards, detailed_feedback=detailed_feedback,
                    disclose_optimum=disclose_optimum, disclose_reward_structure=disclose_reward_structure,
                    secret_offsets=secret_offsets, warp_params=warp_params, warp_rewards=warp_rewards,
                    hide_return_diagnostics=hide_return_diagnostics, encoded_warmup=encoded_warmup,
                    describe_task=describe_task)  # fmt: skip
    entry = get_method(method)  # a bad method fails before the env is made
    entry.mechanisms(**switches)
    values: dict[str, Any] = dict(
        method=method, warmup=warmup, iterations=iterations, top_k=top_k, final_episodes=final_episodes, seed=seed,
        box=tuple(box), decimals=decimals, workers=workers, prompt_params=prompt_params, param_digits=param_digits,
        prompt_layout=prompt_layout, prompt_form=prompt_form, parse_retries=parse_retries, on_llm_failure=on_llm_failure, base_url=base_url, model=model,
        api_key_env=api_key_env, temperature=temperature, max_tokens=max_tokens, timeout=timeout,
        reasoning_effort=reasoning_effort, structured=structured, context_size=context_size, retries=retries,
        **{k: v for k, v in switches.items() if v is not None},
    )  # fmt: skip
    if episodes is not None:
        values["episodes"] = episodes
    t = load_task(task, env_kwargs=env_kwargs, max_episode_steps=max_episode_steps, gym_packages=gym_packages,
                  obs_keys=obs_keys, components=components, diagnostics=diagnostics)  # fmt: skip
    config = build_config(values, task=t)
    run_dir = Path(out) if out is not None else _default_out(t.name, method, seed)
    from .runner import start

    with _progress(progress, f"{t.name} {method}") as events:
        start(config, run_dir, events, chat=chat)
    return load_run(run_dir)


def resume(
    run_dir: Pathish,
    *,
    base_url: str | None = None,
    model: str | None = None,
    api_key_env: str | None = None,
    chat: Any = None,
    progress: bool = False,
) -> SearchResult:
    """Continue an interrupted run with its own secrets and task, then return it (as ``search``).

    The task is rebuilt from the declaration stored with the run: no registration code needs to
    run first.

    Args:
        run_dir: the run directory.
        base_url: continue against this endpoint instead of the run's (recorded with the run).
        model: the model name there (default: the run's).
        api_key_env: the environment variable holding its API key ("" for none; default: the run's).
        chat: a chat object (as in ``search``) that replaces the run's LLM for this session.
        progress: show a progress bar on stderr.

    Raises:
        StoreError, KeyFileError: not a run directory, or its store / key file is damaged.
        ConfigError, LLMError: as ``search``; ConfigError also for an RL baseline run.
    """
    from .baselines.record import refuse_resume
    from .runner import Endpoint
    from .runner import resume as _resume

    refuse_resume(Path(run_dir))  # an RL baseline run has no search to continue
    endpoint = Endpoint(base_url=base_url, model=model, api_key_env=api_key_env)
    with _progress(progress, str(run_dir)) as events:
        _resume(Path(run_dir), events, endpoint=endpoint, chat=chat)
    return load_run(run_dir)


def load_run(run_dir: Pathish) -> SearchResult:
    """A stored run as a ``SearchResult`` (read only; works on unfinished runs too).

    Raises:
        StoreError: not a run directory, or its store is damaged.
        ConfigError: an RL baseline run (``ppprops baseline rl``): it has no search history; or the
            stored configuration names a method unknown in this process (a plugin not installed).
        PPPropsError: the run's ``best_policy.json`` is damaged (``load_policy``).
    """
    from .loop import best_candidate
    from .store import open_store

    run_dir = Path(run_dir)
    with open_store(run_dir) as store:
        stored = store.config()
        if RunKind.of_config(stored) is RunKind.RL:
            raise ConfigError(f"{run_dir} is an RL baseline run ({stored.get('method')}), not a search: "
                              f"`ppprops show {run_dir}` and `ppprops report` read it")  # fmt: skip
        config = RunConfig.from_json(stored)
        history = tuple(store.candidates())
        fe = store.final_eval()
        status = store.status()
    best = best_candidate(list(history)) if history else None
    final = None
    if fe is not None and fe.returns:
        final = Evaluation(task=config.task, returns=tuple(fe.returns), seeds=tuple(fe.seeds), seed=config.seed)
    policy_path = run_dir / POLICY_NAME
    policy = load_policy(policy_path) if policy_path.exists() else None
    return SearchResult(run_dir=run_dir, task=config.task, method=config.method, status=status, config=config, history=history,
                        best_index=None if best is None else best.index, best_return=None if best is None else best.ret,
                        final=final, policy=policy)  # fmt: skip


def evaluate_policy(policy: Pathish | Policy, *, episodes: int = 20, seed: int = 0, workers: int = 1,
                    progress: bool = False) -> Evaluation:
    """Run a policy file on fresh episodes of its task, with no encoding involved.

    The episode seeds are ``ppprops.seeding.final_eval_seeds(seed, episodes)``: with a run's seed
    and its ``final_episodes`` this reproduces the run's final evaluation. The task is rebuilt from
    the declaration in the file (older files: from the task's name). ``progress`` shows a bar of
    episodes on stderr.

    Raises:
        ConfigError: ``episodes`` < 1, or the file does not fit its task.
        PPPropsError: the file is missing or not a ppprops policy file.
    """
    from . import seeding
    from .evaluation import Evaluator
    from .tasks import get_task, task_from_json

    if episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes}")
    pol = policy if isinstance(policy, Policy) else load_policy(policy)
    doc = pol.document
    task = task_from_json(doc["task_spec"]) if doc.get("task_spec") else get_task(str(doc.get("task")))
    if (task.n_s, task.n_a) != (pol.n_s, pol.n_a):
        raise ConfigError(f"policy file {pol.path} has n_s={pol.n_s}, n_a={pol.n_a}; task {task.name} needs {task.n_s}, {task.n_a}")
    from .progress import episode_events
    from .runner import final_returns

    seeds = seeding.final_eval_seeds(seed, episodes)
    with Evaluator(task, workers=workers) as ev, episode_events(enabled=progress, label=f"{task.name} policy eval") as events:
        returns = final_returns(ev, pol.theta, seeds, events)
    return Evaluation(task=task.name, returns=tuple(float(r) for r in returns), seeds=tuple(int(s) for s in seeds), seed=seed)


class _progress:
    """A tqdm bar on stderr while a run goes (``progress=True``), else nothing."""

    def __init__(self, enabled: bool, label: str) -> None:
        from .progress import ProgressEvents

        self._events = ProgressEvents(enabled=enabled, label=label)

    def __enter__(self) -> Any:
        return self._events.__enter__().hooks()

    def __exit__(self, *exc: object) -> None:
        self._events.__exit__(*exc)


__all__ = ["Evaluation", "Policy", "SearchResult", "evaluate_policy", "load_policy", "load_run", "resume", "search"]
