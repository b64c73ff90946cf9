"""Starting and resuming a search in a run directory: short loops over the study (``ppprops.study``).

``start`` makes the run directory (``rundir.create_run``) and runs ``Study.optimize`` on it;
``resume`` reopens one (optionally against another LLM endpoint, ``change_endpoint``) and does the
same. After a ``kill -9`` at any moment, ``resume`` finishes the run with each candidate recorded
once (``ppprops.rundir``, ``ppprops.study``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .client.secrets import Secrets
from .config import RunConfig
from .env_loop import unsaved
from .errors import ConfigError, StoreError
from .evaluation import Fleet, check_parallel
from .events import NO_EVENTS, RunEvents
from .llm.protocol import LLM
from .rundir import POLICY_NAME, create_run, discard_empty_run, final_returns, load_run, missing_parents, new_run_id
from .store import RunStore
from .study import Callback, Study
from .values import FinalEval

__all__ = ["Endpoint", "Limits", "POLICY_NAME", "RunEvents", "change_endpoint", "check_creatable", "check_startable", "create_run",
           "final_returns", "change_limits", "load_run", "new_run_id", "resume", "start"]


def check_creatable(config: RunConfig, run_dir: Path, *, endpoint: bool = True, task: Any = None) -> Any:
    """Every check of a new run or study that needs no env, before anything is written: the
    settings are valid, the output directory is free, the API key variable is set and the endpoint
    answers as an OpenAI-compatible API (``llm.probe``) when the method will call the configured
    endpoint (``endpoint``: False when a model object stands in for it). ``ppprops study create``
    and ``create_study`` run these; ``check_startable`` adds the env's.

    Returns the task (``config.make_task()``, or ``task`` when the caller made it from a
    validated ``config``).

    Raises:
        ConfigError: one line saying what to change.
    """
    from .llm.client import read_api_key
    from .methods import get_method
    from .rundir import check_out

    if task is None:
        config.validate()
        task = config.make_task()
    check_out(run_dir)
    if endpoint and get_method(config.method).uses_llm and config.iterations > 0 and not config.llm.embedded:
        from .llm.probe import probe_endpoint

        probe_endpoint(config.llm, read_api_key(config.llm))
    return task


def check_startable(config: RunConfig, run_dir: Path, *, endpoint: bool = True) -> Any:
    """Every check of a new run that needs no episode, before anything is written: those of
    ``check_creatable`` (settings, output directory, API key, endpoint), then the task has an env
    (a task without one is driven with ask/tell), worker processes can make the env, and the env
    can be made (a simulator extra that is missing, a module that fails to import, a constructor
    that raises).

    Returns the env made by the last check, for the run's episodes: hand it to ``start(env=...)``,
    which closes it (or close it yourself).

    Raises:
        ConfigError: one line saying what to change (a ``MissingExtraError`` names the extra).
    """
    config.validate()
    task = config.make_task()
    if not getattr(task, "has_env", True):
        raise ConfigError(f"task {task.name} has no env, so 'ppprops run' cannot evaluate its policies: drive it with "
                          "'ppprops study create' and 'ppprops ask' / 'ppprops tell' (docs/own-robot.md)")  # fmt: skip
    check_creatable(config, run_dir, endpoint=endpoint, task=task)
    if config.workers > 1:
        check_parallel(task)
    return task.make_env()


def start(
    config: RunConfig,
    run_dir: Path,
    events: RunEvents = NO_EVENTS,
    *,
    secrets: Secrets | None = None,
    llm_gate: AbstractContextManager[object] | None = None,
    llm: LLM | None = None,
    callbacks: Sequence[Callback] = (),
    env: Any = None,
    fleet: Fleet | None = None,
) -> FinalEval | None:
    """Check that the run can start (``check_startable``), create the run directory
    (``create_run``) and run it: warm-up, search, final evaluation, policy file (Algorithm 1 of the
    paper for the prompted methods).

    A loop over the study (``Study.create(...).optimize()``). ``llm_gate`` (e.g. a shared
    semaphore) is held around every LLM request of the run; ``llm`` replaces the configured LLM;
    ``secrets`` replaces freshly drawn ones (tests, controlled grids); ``callbacks`` are called
    after each candidate (``Study.optimize``); ``env`` is the env ``check_startable`` returned,
    when the caller ran the checks itself (they are not run again; the run closes it); ``fleet``
    evaluates each round's candidates instead of the run's own evaluator (``evaluation.Fleet``,
    e.g. ``ray_fleet.RayFleet``).

    Returns:
        The final evaluation (the best search policy on ``final_episodes`` fresh episodes, raw
        returns), or None when ``final_episodes`` is 0.

    A run refused before it recorded anything (its first episode found the env broken, an
    undeclared reward component, a malformed value: no trial told, none failed, no LLM request)
    leaves nothing: its directory is removed (``rundir.discard_empty_run``) and the error is
    raised without the line that names ``resume``, so the corrected command runs with the same
    ``run_dir``.

    Raises:
        ConfigError: an invalid config, an endpoint that does not answer as an OpenAI-compatible
            API, or ``run_dir`` already holds something or cannot be made (nothing is written then).
        LLMError: the endpoint stayed down past the retries (the run is left resumable).
        KeyboardInterrupt: Ctrl-C; the run is marked ``interrupted`` and resumable.
        EpisodeError, PoolError: the env raised or returned a malformed value (left resumable
            once something was recorded; nothing is left otherwise).
        FeedbackKeyError, EpisodeLimitError: the env broke its declaration mid-run (status
            ``stopped: ...``; nothing is left when it was the first episode).
    """
    if env is None:
        env = check_startable(config, run_dir, endpoint=llm is None)
    existed = Path(run_dir).is_dir()  # an empty directory given as --out: left empty again on a refusal
    parents = missing_parents(Path(run_dir))  # and the folders above it that the run makes: removed again
    try:
        study = Study.create(config, run_dir, secrets=secrets, llm=llm, llm_gate=llm_gate, events=events, env=env)
    except BaseException:
        env.close()
        raise
    try:
        with study:
            return study.optimize(callbacks, events, fleet=fleet)
    except Exception as e:
        if not discard_empty_run(run_dir, keep_dir=existed, parents=parents):
            raise
        line = unsaved(str(e), run_dir)
        if line == str(e):
            raise
        raise type(e)(line) from None


@dataclass(frozen=True)
class Endpoint:
    """LLM endpoint settings given to ``resume``; None keeps the run's own. An empty
    ``api_key_env`` removes the key variable (an endpoint that needs no key)."""

    base_url: str | None = None
    model: str | None = None
    api_key_env: str | None = None

    @property
    def given(self) -> bool:
        """True when any setting is given (the run's endpoint changes)."""
        return any(v is not None for v in (self.base_url, self.model, self.api_key_env))


def change_endpoint(store: RunStore, config: RunConfig, endpoint: Endpoint, *, probe: bool = True) -> RunConfig:
    """The run's config with ``endpoint`` applied, validated, probed, stored, and the change recorded.

    The store's config gets the new ``llm.base_url``, ``model`` and ``api_key_env`` (so a later
    plain ``resume`` keeps them), and ``endpoint_changes`` gets one entry (when, after how many
    candidates and LLM calls, from, to). Secrets and key file are untouched. Before anything is
    stored, the new endpoint must answer as an OpenAI-compatible API (``llm.probe``; ``probe``:
    False when a model object stands in for it, or the method calls no LLM). Raises ConfigError
    for settings ``LLMConfig.validate`` refuses or an endpoint that does not answer (nothing is
    changed then); returns ``config`` unchanged if nothing differs.
    """
    llm = replace(
        config.llm,
        base_url=config.llm.base_url if endpoint.base_url is None else endpoint.base_url,
        model=config.llm.model if endpoint.model is None else endpoint.model,
        api_key_env=config.llm.api_key_env if endpoint.api_key_env is None else (endpoint.api_key_env or None),
    )
    llm.validate()
    if llm == config.llm:
        return config
    if probe and llm.base_url and not llm.embedded:
        from .llm.client import read_api_key
        from .llm.probe import probe_endpoint

        probe_endpoint(llm, read_api_key(llm))
    new = replace(config, llm=llm)
    keys = ("base_url", "model", "api_key_env")
    store.change_config(new.to_json(), {
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "candidates": len(store.candidates()),
        "llm_calls": len(store.llm_calls()),
        "from": {k: getattr(config.llm, k) for k in keys},
        "to": {k: getattr(llm, k) for k in keys},
    })  # fmt: skip
    return new


@dataclass(frozen=True)
class Limits:
    """The search's limits given to ``resume``: its ``iterations`` and stop rules
    (``stopping.StopRules``: ``target_return``, ``time_limit_s``, ``patience``); None keeps the run's."""

    iterations: int | None = None
    target_return: float | None = None
    time_limit_s: float | None = None
    patience: int | None = None

    @property
    def given(self) -> bool:
        """True when any limit is given."""
        return any(v is not None for v in (self.iterations, self.target_return, self.time_limit_s, self.patience))


def change_limits(store: RunStore, config: RunConfig, limits: Limits) -> tuple[RunConfig, str | None]:
    """The run's config with ``limits`` applied, validated and stored; a search that ended (its
    budget spent, or a stop rule) and that the new limits leave room for goes on
    (``stopping.continue_search``: status ``running`` again). Returns the config and a note line
    when the search goes on. Raises ConfigError for a limit refused (nothing is changed then)."""
    from .status import RunStatus
    from .stopping import continue_search

    given = {k: getattr(limits, k) for k in ("target_return", "time_limit_s", "patience") if getattr(limits, k) is not None}
    new = replace(config, stop=replace(config.stop, **given), iterations=config.iterations if limits.iterations is None else limits.iterations)
    status, reason = store.run_status()
    goes_on = continue_search(store, new.stop, warmup=new.warmup, iterations=new.iterations, old_iterations=config.iterations,
                              stopped=reason if status is RunStatus.STOPPED else None)  # fmt: skip
    if new != config:
        store.change_config(new.to_json())
    if goes_on is None:
        return new, None
    note, state = goes_on
    store.set_stop_state(state)
    store.set_status(RunStatus.RUNNING)
    return new, note


def resume(
    run_dir: Path,
    events: RunEvents = NO_EVENTS,
    *,
    llm_gate: AbstractContextManager[object] | None = None,
    endpoint: Endpoint | None = None,
    limits: Limits | None = None,
    llm: LLM | None = None,
    callbacks: Sequence[Callback] = (),
) -> FinalEval | None:
    """Continue a run with its own secrets: every recorded candidate is kept, the rest is run,
    then the final evaluation. ``endpoint`` continues it against a corrected or different LLM
    endpoint (``change_endpoint``, which probes it first); ``limits`` changes the search's
    iterations and stop rules, and continues a search that ended when they leave room
    (``change_limits``); ``llm`` replaces the run's LLM for this session. Raises StoreError for a missing or foreign directory or key file, ConfigError for a
    bad endpoint (nothing is changed then) or a study of a task without env, LLMError when the
    endpoint stays down."""
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    store, config, secrets = load_run(run_dir)
    try:
        changes = (endpoint is not None and endpoint.given) or (limits is not None and limits.given)
        if changes and not getattr(config.make_task(), "has_env", True):  # refused by optimize below: change nothing first
            raise ConfigError(f"{run_dir} is a study of a task without env, which 'ppprops resume' cannot run: its next "
                              f"trials come from 'ppprops ask {run_dir}'")  # fmt: skip
        if endpoint is not None and endpoint.given:
            from .methods import get_method

            config = change_endpoint(store, config, endpoint, probe=llm is None and get_method(config.method).uses_llm)
        if limits is not None and limits.given:
            config, note = change_limits(store, config, limits)
            if note is not None:
                events.on_notice(note)
        study = Study(Path(run_dir), store, config, secrets, llm=llm, llm_gate=llm_gate, events=events)
    except BaseException:
        store.close()
        raise
    with study:
        return study.optimize(callbacks, events)
