"""The Python API: one call runs a search and returns its result; the same objects come back from a
resumed run, a stored run and a policy evaluation.

    import ppprops

    result = ppprops.search("CartPole", method="pp", seed=0, out="runs/x", evaluation={"final_episodes": 20})
    result.final.mean, result.policy.W        # final-evaluation mean return; W of shape (n_s, n_a)
    action = result.policy(obs)               # the deployable policy on a raw env observation

``search`` takes a task in every form ``ppprops run`` does, and more: a paper task name, a
Gymnasium id, ``module:EnvId`` or ``module:attr``, a task file path, an env factory (a class or a
function returning a Gymnasium env), or a ``TaskSpec`` / ``Task``; options come in groups (``llm``,
``privacy``, ``prompt``, ``evaluation``, ``method_options``, ``task_options``), each a mapping
keyed like the ``ppprops run`` flags. It is a short loop over a ``Study`` (``create_study``,
``load_study``), whose public ask/tell serves a robot that ppprops cannot step itself.

Errors are ``ppprops.errors.PPPropsError`` subclasses with a one-line message (``ConfigError`` for
bad input, ``LLMError`` when the endpoint stays down, ``StoreError`` for run directories);
nothing here prints unless ``progress=True``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypedDict, Unpack

import numpy as np
from numpy.typing import NDArray

from .config import RunConfig
from .errors import ConfigError
from .llm.protocol import LLM
from .policy_file import Policy, load_policy
from .rundir import open_run
from .status import RunKind
from .study import Study
from .tasks.options import TaskOptions
from .values import Candidate

Pathish = str | os.PathLike[str]
TaskLike = Any  # str | os.PathLike | Callable[..., gymnasium.Env] | TaskSpec | Task (see ppprops.tasks.load_task)


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
    encoded form as the LLM saw it, and its ``source``: warmup, llm, fallback, ..., and ``reeval``
    for the selection stage's re-evaluations). ``best_index`` is the candidate handed over
    (``loop.select_best``) and ``best_return`` its search-time mean return; ``final`` the final evaluation of it on fresh
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


class StudyOptions(TypedDict, total=False):
    """The options of ``search`` and ``create_study`` (every key optional; paper Sec. III's settings).

    Options come in groups, each a mapping whose keys are the ``ppprops run`` flags of that group
    with underscores (``ppprops run --help``); the groups are derived from the settings themselves
    (``ppprops.settings.api_groups``)::

        ppprops.search("CartPole", method="pp", warmup=5, iterations=20, seed=0, out="runs/x",
                       llm={"base_url": "http://localhost:11434/v1", "model": "gpt-oss:20b"},
                       prompt={"top_k": 10, "form": "chat"}, evaluation={"final_episodes": 20, "workers": 2},
                       privacy={"scale_rewards": False})

    Keys:
        method: a search method of the registry (``ppprops.methods``): ``vanilla``, ``pe``, ``df``,
            ``pp`` (default), ``pp-hardened``, ``r2po``, ``random`` or ``cmaes``.
        warmup: random warm-up policies (default 10).
        iterations: LLM proposals (r2po: LLM calls; random, cmaes: samples) after the warm-up (default 50).
        seed: the run seed (episode seeds, with the run's key; never the secrets). None (default)
            draws one from the OS (stored with the run).
        box: (low, high), the feasible range of every raw parameter (default (-6, 6)).
        llm: the LLM: None for the embedded model; the endpoint's settings as a mapping or an
            ``LLMConfig`` (``base_url``, ``model``, ``api_key_env``, ``temperature``, ``max_tokens``,
            ``timeout``, ``reasoning_effort``, ``structured``, ``context_size``, ``retries``,
            ``retry_base_delay``, ``retry_max_delay``, ``retry_after_cap``, ``on_llm_failure``); or a
            model object, a ``ppprops.llm.LLM`` (``endpoints``, ``send(request, *, seed)`` returning a
            ``ppprops.llm.Exchange``, ``close()``; the caller keeps it; one that serves the
            completions endpoint gets the document form under ``form="auto"``). Every exchange is
            recorded like an endpoint's.
        privacy: mechanism switches over the method's preset (paper Sec. II; docs/threat-model.md):
            ``encode_params`` (Eq. 5), ``scale_rewards`` (Eq. 7-8), ``detailed_feedback``,
            ``disclose_optimum``, ``disclose_reward_structure``, ``describe_task`` and the hardening
            switches, each True/False (None keeps the preset's).
        prompt: ``top_k`` (history entries shown, best last, Eq. 9; 0 keeps all), ``form``
            (``auto``, ``chat``, ``document``), ``params`` (``list``/``indexed``), ``digits``,
            ``layout``, ``decimals``, ``parse_retries``, ``explore`` (the document form samples hotter
            after 3 LLM iterations without a new best; default True).
        evaluation: ``episodes`` per candidate (default: the method's, 1; 20 for r2po),
            ``final_episodes`` (fresh episodes for the best policy, default 20), ``workers``
            (processes running episodes; results identical to one), ``select_top`` and
            ``select_episodes`` (the selection stage: the top candidates of the search run again on
            fresh episodes and the best pooled mean is handed over; default 5 x 10, 0 for a task
            without an env; ``select_top=0`` hands over the best search-time return).
        stop: when the search ends before its budget (``ppprops.stopping``): ``target_return`` (a raw
            return), ``time_limit`` (``"20m"``, ``"2h"`` or seconds), ``patience`` (candidates in a row
            without a better return); the selection stage and the final evaluation still run.
        method_options: the method's own options (``cmaes``: ``popsize``, ``sigma0``).
        init_policies: policies to evaluate first, in the warm-up's first places (``ppprops.warm_start``):
            each a path to a policy file of this task or to a JSON object with ``W`` and ``b`` (or
            ``theta``), such a mapping, or D numbers (the flat theta).
        task_options: for a task that is not a paper task: ``env_kwargs``, ``max_episode_steps``,
            ``gym_packages``, ``obs_keys``, ``components``, ``diagnostics`` (as the flags of the same names).
        policy: the policy family, for any task: ``"linear"`` (the paper's), ``"mlp:16,16"``, a mapping
            ``{"kind": "mlp", "hidden": [16], "activation": "tanh"}`` or a ``ppprops.policy.PolicySpec``
            (default: the task's declared family, linear unless its task file has a ``[policy]`` table).
        activation: ``"tanh"`` or ``"relu"``, the hidden layers' activation of an mlp policy.
    """

    method: str
    warmup: int
    iterations: int
    seed: int | None
    box: tuple[float, float]
    policy: Any
    activation: Literal["tanh", "relu"] | None
    llm: Any
    privacy: Mapping[str, bool | None] | None
    prompt: Any
    evaluation: Any
    stop: Any
    method_options: Mapping[str, Any] | None
    init_policies: Sequence[Any] | None
    task_options: Any


def _group_values(group: str, given: Any, *, fields: bool = False) -> dict[str, Any]:
    """One option group (a mapping, or a settings object such as ``LLMConfig``) as setting keys
    (``fields``: as the field names of the settings' schema class).

    Raises ConfigError for a value that is not a mapping or an unknown key (naming the group and
    the closest key)."""
    import difflib
    from dataclasses import asdict, is_dataclass

    from .settings import api_groups

    known = api_groups()[group]
    if given is None:
        return {}
    if is_dataclass(given) and not isinstance(given, type):  # a settings object: its field names
        by_field = {s.field: name for name, s in known.items()}
        given = {by_field.get(k, k): v for k, v in asdict(given).items()}
    if not isinstance(given, Mapping):
        raise ConfigError(f"{group}= must be a mapping of options (e.g. {group}={{...}}), got {type(given).__name__}")
    out: dict[str, Any] = {}
    for key, value in given.items():
        if key not in known:
            close = difflib.get_close_matches(str(key), list(known), n=1)
            hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(known)}"
            raise ConfigError(f"{group}: unknown option {key!r} ({hint})")
        out[known[key].field if fields else known[key].key] = tuple(value) if isinstance(value, list) else value
    return out


def _build(task: TaskLike, options: StudyOptions, own: tuple[str, ...] = ()) -> tuple[RunConfig, LLM | None]:
    """The RunConfig of ``search``'s / ``create_study``'s arguments, and the model ``llm`` names when
    it is one (an ``LLM``) rather than settings. ``own``: the caller's own keywords (``out``, ...),
    named in the error for an unknown option. Raises ConfigError for an unknown option."""
    import difflib

    from .methods import get_method
    from .seeding import draw_seed
    from .settings import build_config
    from .tasks import load_task

    unknown = sorted(set(options) - set(StudyOptions.__annotations__))
    if unknown:
        known = [*StudyOptions.__annotations__, *own]
        close = difflib.get_close_matches(unknown[0], known, n=1)
        hint = f"did you mean {close[0]}?" if close else f"known: {', '.join(known)}"
        raise ConfigError(f"unknown option {unknown[0]!r} ({hint})")
    method = options.get("method", "pp")
    llm = options.get("llm")
    model: LLM | None = None
    if isinstance(llm, LLM):
        model, llm = llm, None
    switches = dict(options.get("privacy") or {})
    get_method(method).mechanisms(**switches)  # a bad method or switch fails before the env is made
    seed = options.get("seed")
    values: dict[str, Any] = {"method": method, "warmup": options.get("warmup", 10), "iterations": options.get("iterations", 50),
                              "box": tuple(options.get("box", (-6.0, 6.0))), "seed": draw_seed() if seed is None else seed}  # fmt: skip
    for group, given in (("llm", llm), ("prompt", options.get("prompt")), ("evaluation", options.get("evaluation")),
                         ("stop", options.get("stop"))):
        values.update(_group_values(group, given))
    values.update({k: v for k, v in switches.items() if v is not None})
    if options.get("method_options"):
        values["method_options"] = dict(options["method_options"] or {})
    t = load_task(task, options=TaskOptions(**_group_values("task_options", options.get("task_options"), fields=True),
                                            policy=options.get("policy"), activation=options.get("activation")))
    config = build_config(values, task=t)
    given = list(options.get("init_policies") or ())
    if given:
        import os
        from dataclasses import replace

        from .warm_start import init_thetas

        labels = tuple(str(p) if isinstance(p, str | os.PathLike) else "python" for p in given)
        config = replace(config, init_policy=labels, init_thetas=init_thetas(given, t, box=config.box, warmup=config.warmup))
    return config, model


def search(task: TaskLike, *, out: Pathish | None = None, callbacks: Sequence[Callable[[Candidate, Study], bool | None]] = (),
           progress: bool = False, **options: Unpack[StudyOptions]) -> SearchResult:
    """Run a policy search (paper Sec. II-E, Algorithm 1; settings of Sec. III) on ``task`` and return its result.

    A short loop over a study (``create_study``: ask, evaluate on the task's env, tell; then the
    final evaluation and the policy file)::

        result = ppprops.search("CartPole", method="pp", warmup=5, iterations=20, out="runs/x",
                                evaluation={"final_episodes": 20})

    Args:
        task: a paper task name (``"Ant-Ultra"``), a Gymnasium id, ``"module:EnvId"`` or
            ``"module:attr"``, a task file path (``.toml``), an env factory (an ``Env`` class or a
            function returning an env, called with ``task_options["env_kwargs"]``), a ``TaskSpec``
            or a ``Task``. A factory with no importable name (a lambda, a local function) works in
            this process only; one defined at the top level of a module (or of the script being
            run) also works with ``workers > 1``, ``resume`` and ``policy eval`` from a fresh process.
        out: the run directory (default ``runs/<run id>``); it must not hold anything yet.
        callbacks: called after each told candidate as ``callback(candidate, study)``; one returning
            ``False`` stops the search cleanly (status ``stopped: stopped by a callback``).
        progress: show a progress bar on stderr.
        **options: the run's options (``StudyOptions``): ``method``, ``warmup``, ``iterations``,
            ``seed``, ``box``, and the groups ``llm``, ``privacy``, ``prompt``, ``evaluation``,
            ``method_options``, ``task_options``.

    Returns:
        The finished run (``SearchResult``).

    Raises:
        ConfigError: bad settings or task (one line: an unknown option or id, a module that fails to
            import and why, an occupied ``out``).
        LLMError: the endpoint stayed down past the retry bound (the run is saved: ``resume`` it).
        StoreError: the run directory cannot be written.
        MissingExtraError: the task needs an extra that is not installed (``mujoco``, ``robotics``, ...).
    """
    from .evaluation import exit_if_importing_main_in_a_worker

    exit_if_importing_main_in_a_worker()  # an unguarded script re-imported by a worker must not start a second run
    config, model = _build(task, options, ("out", "callbacks", "progress"))
    from .naming import default_run_dir
    from .runner import start

    run_dir = Path(out) if out is not None else default_run_dir(config)
    with _progress(progress, f"{config.task} {config.method}") as events:
        start(config, run_dir, events, llm=model, callbacks=callbacks)
    return load_run(run_dir)


def create_study(task: TaskLike, *, storage: Pathish | None = None, **options: Unpack[StudyOptions]) -> Study:
    """A new study in ``storage`` (a run directory, default ``runs/<run id>``), to drive by hand:
    ``trial = study.ask()``, evaluate ``trial.theta`` (or ``trial.W``, ``trial.b``) on your robot
    or simulator, ``study.tell(trial, episode_return, components=..., diagnostics=...)``, until
    ``study.done``; then ``study.finalize()``. ``task`` and ``options`` (``StudyOptions``) as for
    ``search``. Use it in a ``with`` block (it holds the store and, once asked, the LLM client).
    ``ppprops.load_study(storage)`` reopens it in another process, after a restart or a crash
    (``ppprops.study``).

    Raises:
        ConfigError: bad settings or task, an occupied ``storage``, an endpoint that does not
            answer as an OpenAI-compatible API (``llm.probe``; nothing is written then).
    """
    from .naming import default_run_dir
    from .runner import check_creatable

    config, model = _build(task, options, ("storage",))
    run_dir = Path(storage) if storage is not None else default_run_dir(config)
    check_creatable(config, run_dir, endpoint=model is None)  # a study that cannot start leaves nothing
    return Study.create(config, run_dir, llm=model)


def load_study(storage: Pathish, *, llm: LLM | None = None) -> Study:
    """The study stored in ``storage`` (made by ``create_study``, ``ppprops study create`` or any
    run), as it was left: a pending trial is asked again without a second LLM call. ``llm``: a model
    (``ppprops.llm.LLM``) replacing the configured one in this process (the caller keeps it).

    Raises:
        StoreError, KeyFileError: not a run directory, or its store / key file is damaged.
        ConfigError: an RL baseline run, or a task or method unknown in this process.
    """
    from .baselines.record import refuse_resume

    refuse_resume(Path(storage))
    return Study.load(Path(storage), llm=llm)


def resume(
    run_dir: Pathish,
    *,
    base_url: str | None = None,
    model: str | None = None,
    api_key_env: str | None = None,
    llm: LLM | None = None,
    iterations: int | None = None,
    stop: Mapping[str, Any] | None = None,
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
        llm: a model (``ppprops.llm.LLM``, as in ``search``) that replaces the run's LLM for this session.
        iterations: the search's iterations (default: the run's); more than it ran continues a
            search that ended (after its selection stage, which is kept).
        stop: stop rules replacing the run's, keyed as ``search``'s ``stop`` group
            (``target_return``, ``time_limit``, ``patience``); a search a rule ended goes on when
            the new ones leave room (``ppprops.stopping``).
        progress: show a progress bar on stderr.

    Raises:
        StoreError, KeyFileError: not a run directory, or its store / key file is damaged.
        ConfigError, LLMError: as ``search``; ConfigError also for an RL baseline run.
    """
    from .baselines.record import refuse_resume
    from .runner import Endpoint, Limits
    from .runner import resume as _resume
    from .stopping import StopRules

    refuse_resume(Path(run_dir))  # an RL baseline run has no search to continue
    endpoint = Endpoint(base_url=base_url, model=model, api_key_env=api_key_env)
    rules = StopRules(**{k: v for k, v in _group_values("stop", stop, fields=True).items()})
    limits = Limits(iterations=iterations, target_return=rules.target_return, time_limit_s=rules.time_limit_s, patience=rules.patience)
    with _progress(progress, str(run_dir)) as events:
        _resume(Path(run_dir), events, endpoint=endpoint, limits=limits, llm=llm)
    return load_run(run_dir)


def load_run(run_dir: Pathish) -> SearchResult:
    """A stored run as a ``SearchResult`` (read only; works on unfinished runs too).

    Raises:
        StoreError: not a run directory, or its store is damaged.
        ConfigError: an RL baseline run (``ppprops baseline rl``): it has no search history; or the
            stored configuration names a method unknown in this process (a plugin not installed).
        PPPropsError: the run's ``best_policy.json`` is damaged (``load_policy``).
    """
    from .loop import search_candidates, select_best

    run_dir = Path(run_dir)
    with open_run(run_dir) as run:
        if run.kind is RunKind.RL:
            raise ConfigError(f"{run_dir} is an RL baseline run ({run.stored.get('method')}), not a search: "
                              f"`ppprops show {run_dir}` and `ppprops report` read it")  # fmt: skip
        config = run.config
        history = tuple(run.store.candidates())
        fe = run.store.final_eval()
        status = run.store.status()
    best = select_best(list(history)) if search_candidates(list(history)) else None
    final = None
    if fe is not None and fe.returns:
        final = Evaluation(task=config.task, returns=tuple(fe.returns), seeds=tuple(fe.seeds), seed=config.seed)
    policy = load_policy(run.policy_path) if run.policy_path.exists() else None
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
        ConfigError: ``episodes`` < 1, the file does not fit its task, or its task has no env.
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
    if not task.has_env:  # NoEnvError before any progress bar or worker, so the error is the only line
        task.make_env()
    if task.policy != pol.spec:
        raise ConfigError(f"policy file {pol.path} holds a {pol.spec.label()} policy; its task {task.name} declares {task.policy.label()}")
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


__all__ = ["Evaluation", "Policy", "SearchResult", "Study", "StudyOptions", "create_study", "evaluate_policy", "load_policy", "load_run", "load_study",
           "resume", "search"]
