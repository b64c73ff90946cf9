"""Starting, resuming and finishing a run directory: the client-side orchestration.

A run directory holds ``run.sqlite`` (the store), ``secrets.key`` (mode 0600) and, once
finished, ``best_policy.json``.

Crash safety: the directory is built under a temporary name and renamed into place, so a run
killed while starting leaves either nothing at ``--out`` or a complete, resumable directory.
After that every step is a committed store row or an atomic file rename, so ``resume`` after a
``kill -9`` at any moment finishes the run with each candidate recorded once.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, ExitStack, closing, contextmanager, nullcontext
from contextvars import ContextVar
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from . import seeding
from .client.hardening import codec_for, generate_secrets
from .client.secrets import Secrets
from .config import RunConfig
from .errors import ConfigError, LLMError, StoreError
from .evaluation import EpisodeLimitError, Evaluator, WorkerError, check_parallel
from .fileio import write_json_atomic
from .llm.client import ChatClient, Exchange, RequestShape
from .loop import Phase, best_candidate, run_loop
from .methods import get_method
from .policy_file import policy_document
from .proposers.base import StopSearch
from .proposers.uniform import warmup_sampler
from .status import RunStatus
from .store import DB_NAME, KEY_NAME, RunStore, open_store
from .strategies import SearchSetup, search_phase
from .tasks import FeedbackKeyError, Task
from .values import Candidate, Feedback, FinalEval

# Errors of an env that breaks its task's declaration mid-run: the run stops (not resumable as is).
BROKEN_TASK = (FeedbackKeyError, EpisodeLimitError, WorkerError)
CHAT_TEMPLATE_MARGIN = 32  # tokens the chat template adds around a single user message
POLICY_NAME = "best_policy.json"


def _ignore(*args: object) -> None:
    return None


@dataclass(frozen=True)
class RunEvents:
    """Hooks for progress display; the runner itself prints nothing.

    on_start(done, total): candidates recorded and planned; on_candidate(candidate, LLM latency in
    seconds or None, best return so far); on_llm_loading() and on_llm_ready(seconds) around the
    start of the embedded model; on_final_start(episodes) and on_final_episode(done) during the
    final evaluation; on_final(final evaluation) at the end.
    """

    on_start: Callable[[int, int], None] = _ignore
    on_candidate: Callable[[Candidate, float | None, float], None] = _ignore
    on_final: Callable[[FinalEval], None] = _ignore
    on_llm_loading: Callable[[], None] = _ignore
    on_llm_ready: Callable[[float], None] = _ignore
    on_final_start: Callable[[int], None] = _ignore
    on_final_episode: Callable[[int], None] = _ignore


class ChatModel(Protocol):
    """What the runner asks an LLM through: the recording ``ChatClient`` or any object like it.

    ``complete`` sends one prompt (``messages``: OpenAI chat messages) for a vector of ``D`` numbers
    and returns the ``Exchange`` (request and answer text, recorded in the store, so the audit
    sees it); ``count_tokens`` measures a prompt (R2PO's context check); ``close`` ends it. A model
    that also has ``complete_document(prompt, *, D, seed, grammar)`` (``ChatClient`` does) can be
    sent the document form; without it, ``--prompt-form auto`` uses the chat form.
    """

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        """Send ``messages`` asking for ``D`` numbers; the Exchange holds the request, answer and errors."""
        ...

    def count_tokens(self, text: str) -> int:
        """An estimate of ``text``'s length in the model's tokens (never under-counted on purpose)."""
        ...

    def close(self) -> None:
        """Release the endpoint (stop an embedded server this object started)."""
        ...


# A chat model for every run started in this context (see ``use_chat``); None: the configured LLM.
_CHAT_FACTORY: ContextVar[Callable[[RunConfig], ChatModel] | None] = ContextVar("ppprops_chat_factory", default=None)


@contextmanager
def use_chat(factory: Callable[[RunConfig], ChatModel]) -> Iterator[None]:
    """Within the block, runs talk to ``factory(config)`` instead of their configured endpoint.

    For offline stand-ins (``ppprops.privacy.simulate.offline_llm``) and tests; a single run takes
    its chat model as the ``chat`` argument of ``start`` / ``resume`` instead.
    """
    token = _CHAT_FACTORY.set(factory)
    try:
        yield
    finally:
        _CHAT_FACTORY.reset(token)


def new_run_id(config: RunConfig) -> str:
    """A fresh run id, ``<task>__<method>__<seed>__<8 hex digits>`` (random, so two runs never share one)."""
    return f"{config.task}__{config.method}__{config.seed}__{uuid.uuid4().hex[:8]}"


def create_run(config: RunConfig, run_dir: Path, secrets: Secrets | None = None) -> tuple[RunStore, Secrets]:
    """Make the directory, key file and store. Refuses a directory that already holds something.

    ``secrets`` is for tests and controlled experiments; normally they are drawn fresh here.
    Everything is written under a temporary sibling name first, then renamed to ``run_dir``.
    The stored config holds the task's whole declaration (``task_spec``), so the run can be resumed
    and evaluated in any process; a task's env and info keys are checked before anything is written.
    """
    config.validate()
    task = config.make_task()
    if config.task_spec is None and task.spec is not None:
        config = replace(config, task_spec=task.spec.to_json())
    if config.workers > 1:
        check_parallel(task)  # before the directory: a pool that could never start
    run_dir = Path(run_dir)
    if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
        what = "another run" if (run_dir / DB_NAME).exists() else "files"
        raise ConfigError(f"output directory {run_dir} already holds {what}; choose a new --out or use 'ppprops resume'")
    run_id = new_run_id(config) if secrets is None else secrets.run_id
    if secrets is None:
        secrets = generate_secrets(run_id, task, config)  # paper secrets, plus offsets/warp when hardened
    elif len(secrets.a) != task.D:
        raise ConfigError(f"given secrets have D={len(secrets.a)}, task {task.name} needs {task.D}")
    tmp = run_dir.parent / f".{run_dir.name}.{uuid.uuid4().hex[:8]}.creating"
    try:
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as e:
        raise ConfigError(f"cannot create output directory {run_dir}: {e.strerror}") from None
    try:
        try:
            secrets.save(tmp / KEY_NAME)
        except OSError as e:
            raise StoreError(f"cannot write the key file in {run_dir}: {e.strerror}") from None
        with RunStore(tmp / DB_NAME) as store:  # closed (the WAL checkpointed) before the directory moves
            store.init_run(run_id, config.to_json(), secrets.fingerprint())
        try:
            os.rename(tmp, run_dir)  # onto a missing or empty directory, atomically
        except OSError as e:
            if e.errno in (errno.ENOTEMPTY, errno.EEXIST):
                raise ConfigError(f"output directory {run_dir} was filled meanwhile; choose a new --out") from None
            raise StoreError(f"cannot create output directory {run_dir}: {e.strerror}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return open_store(run_dir), secrets


def load_run(run_dir: Path) -> tuple[RunStore, RunConfig, Secrets]:
    """The open store, config and secrets of a run directory; the caller closes the store
    (``with store:``). Nothing stays open when this raises.

    Raises:
        StoreError: not a run directory, or a damaged store.
        KeyFileError: the key file is missing, damaged, or belongs to another run.
        ConfigError: the stored config names a task that cannot be made here.
    """
    store = open_store(run_dir)
    try:
        config = RunConfig.from_json(store.config())
        task = config.make_task()
        secrets = Secrets.load(Path(run_dir) / KEY_NAME, run_id=store.run_id(), D=task.D, fingerprint=store.key_fingerprint())
    except BaseException:
        store.close()
        raise
    return store, config, secrets


@contextmanager
def chat_client(config: RunConfig, events: RunEvents = RunEvents()) -> Iterator[ChatClient]:
    """The configured endpoint, or the embedded llama.cpp server started for the duration
    (``events.on_llm_loading`` / ``on_llm_ready`` around its start). Raises ConfigError when the
    named API-key variable is empty, LLMError when the embedded server fails to start."""
    llm = config.llm
    with ExitStack() as stack:
        if llm.embedded:
            from .llm.embedded import EmbeddedServer

            events.on_llm_loading()
            t0 = time.monotonic()
            server = stack.enter_context(EmbeddedServer(context_size=llm.context_size))
            events.on_llm_ready(time.monotonic() - t0)
            client = ChatClient(llm, base_url=server.base_url, api_key="not-needed", shape=RequestShape.for_config(llm))
        else:
            api_key = "not-needed"
            if llm.api_key_env:
                api_key = os.environ.get(llm.api_key_env, "")
                if not api_key:
                    raise ConfigError(f"--api-key-env names {llm.api_key_env}, but that environment variable is empty or unset")
            assert llm.base_url is not None and llm.model is not None
            client = ChatClient(llm, base_url=llm.base_url, api_key=api_key, shape=RequestShape.for_config(llm))
        try:
            yield client
        finally:
            client.close()


def execute(
    run_dir: Path,
    store: RunStore,
    config: RunConfig,
    secrets: Secrets,
    events: RunEvents = RunEvents(),
    *,
    llm_gate: AbstractContextManager[object] | None = None,
    chat: ChatModel | None = None,
) -> FinalEval | None:
    """Run (or continue) the search, then the final evaluation, then write the policy file.

    ``chat`` replaces the configured LLM (the caller keeps and closes it). Returns the final
    evaluation (None when ``final_episodes`` is 0). A run that stopped on purpose
    (``stopped: <reason>``) is finished without continuing its search. Raises LLMError when the
    endpoint stays down (the run is left resumable); a KeyboardInterrupt marks the run
    ``interrupted`` (resumable) and propagates. An env that breaks its declaration mid-run (an
    info key gone, an episode that never ends) stops the run (status ``stopped: ...``) and
    raises that one-line error.
    """
    task = config.make_task()
    method = get_method(config.method)
    codec = codec_for(secrets, task, config)  # every mechanism of the config, hardening included
    done = store.candidates()
    total = config.warmup + config.iterations
    events.on_start(len(done), total)
    stored, reason = RunStatus.parse(store.status())
    status, why = (RunStatus.STOPPED, reason) if stored is RunStatus.STOPPED else (RunStatus.FINISHED, "")
    if status is RunStatus.STOPPED and len(done) < total:
        total = len(done)  # a run stopped on purpose (e.g. context overflow) is not continued
    if stored is RunStatus.INTERRUPTED:
        store.set_status(RunStatus.RUNNING)
    try:
        with Evaluator(task, workers=config.workers) as evaluator, ExitStack() as stack:

            def evaluate(theta: np.ndarray, index: int) -> tuple[Feedback, Sequence[int]]:
                seeds = seeding.episode_seeds(config.seed, index, config.episodes)
                return evaluator.evaluate(theta, seeds), seeds

            if len(done) < total:
                warmup = warmup_sampler(task.D, config, codec)  # the paper's raw box, or an encoded one (hardened)
                phases = [Phase("warmup", warmup, config.warmup)]
                if config.iterations > 0:
                    chat_fn = None
                    if method.uses_llm:
                        store.begin_llm_session()  # a fresh client: the audit replays its adaptations from here
                        model = chat
                        if model is None:
                            factory = _CHAT_FACTORY.get()
                            made = factory(config) if factory is not None else LazyChat(config, llm_gate, events)
                            model = stack.enter_context(closing(made))
                        chat_fn = lambda: model  # noqa: E731
                    setup = SearchSetup(task=task, config=config, codec=codec, evaluator=evaluator, store=store, chat=chat_fn)
                    phases.append(search_phase(method, setup))
                search = phases[-1].proposer if len(phases) > 1 else None
                best_so_far = [max((c.ret for c in done if math.isfinite(c.ret)), default=-np.inf)]

                def on_candidate(c: Candidate) -> None:
                    if math.isfinite(c.ret):  # a numerical fault is never the best so far
                        best_so_far[0] = max(best_so_far[0], c.ret)
                    latency = getattr(search, "last_latency", None) if c.source != "warmup" else None
                    events.on_candidate(c, latency, best_so_far[0])

                try:
                    done = run_loop(phases, evaluate=evaluate, codec=codec, store=store, done=done, on_candidate=on_candidate)
                except StopSearch as stop:
                    done = store.candidates()
                    status, why = RunStatus.STOPPED, stop.reason
                except LLMError as e:  # the endpoint stayed down past the retry bound: stop, resumable
                    raise LLMError(f"{e}; the run is saved: continue with 'ppprops resume {run_dir}'") from e
                except BROKEN_TASK as e:  # the env broke its declaration
                    store.set_status(RunStatus.STOPPED, str(e))
                    raise
            try:
                fe = finish(run_dir, store, config, task, evaluator, done, status=status, reason=why, events=events)
            except BROKEN_TASK as e:
                store.set_status(RunStatus.STOPPED, str(e))
                raise
    except KeyboardInterrupt:
        _mark_interrupted(store)
        raise
    events.on_final(fe) if fe is not None else None
    return fe


def _mark_interrupted(store: RunStore) -> None:
    """Best effort: ``show`` says interrupted instead of running; resume continues it either way."""
    try:
        if RunStatus.parse(store.status())[0] is RunStatus.RUNNING:
            store.set_status(RunStatus.INTERRUPTED)
    except (StoreError, KeyboardInterrupt):
        pass


def finish(
    run_dir: Path, store: RunStore, config: RunConfig, task: Task, evaluator: Evaluator, done: list[Candidate],
    *, status: RunStatus = RunStatus.FINISHED, reason: str = "", events: RunEvents = RunEvents(),
) -> FinalEval | None:
    """Final evaluation of the best candidate (``config.final_episodes`` fresh seeds), the policy
    file, then ``status`` in the store. A final evaluation already stored for the same candidate
    is kept. Raises StoreError when the policy file cannot be written (the run stays resumable)."""
    best = best_candidate(done)
    fe = store.final_eval()
    if fe is None or fe.candidate_index != best.index:
        seeds = seeding.final_eval_seeds(config.seed, config.final_episodes)
        fe = FinalEval(candidate_index=best.index, returns=final_returns(evaluator, best.params, seeds, events), seeds=tuple(seeds))
        store.set_final_eval(fe)
    final = {"mean": fe.mean, "std": fe.std, "episodes": len(fe.returns), "seed": config.seed} if fe.returns else None
    search = {"run_id": store.run_id(), "method": config.method, "seed": config.seed, "return": best.ret, "candidate": best.index}
    path = Path(run_dir) / POLICY_NAME
    for stale in Path(run_dir).glob(f".{POLICY_NAME}.*.tmp"):  # left by a run killed mid-write
        stale.unlink(missing_ok=True)
    try:
        write_json_atomic(path, policy_document(task, best.params, env=None if task.discrete else evaluator.env, search=search,
                                                  final_eval=final))
    except OSError as e:
        raise StoreError(f"cannot write {path}: {e.strerror or e}; then continue with 'ppprops resume {run_dir}'") from None
    store.set_status(status, reason)
    return fe


def final_returns(evaluator: Evaluator, theta: np.ndarray, seeds: Sequence[int], events: RunEvents = RunEvents()) -> tuple[float, ...]:
    """Episode returns of ``theta`` on ``seeds``, in order, reported to ``events`` as they come.

    Episodes run in chunks of ``evaluator.workers`` (one per worker at a time); each episode
    depends only on its seed, so the returns equal one ``evaluate(theta, seeds)`` call.
    """
    if not seeds:
        return ()
    events.on_final_start(len(seeds))
    returns: list[float] = []
    chunk = max(1, evaluator.workers)
    for i in range(0, len(seeds), chunk):
        returns += evaluator.evaluate(theta, seeds[i : i + chunk]).episode_returns
        events.on_final_episode(len(returns))
    return tuple(returns)


class LazyChat:
    """Starts the LLM only when the first LLM iteration asks, so warm-up never waits for it."""

    def __init__(self, config: RunConfig, gate: AbstractContextManager[object] | None = None,
                 events: RunEvents = RunEvents()) -> None:  # fmt: skip
        self.config = config
        self.gate = gate if gate is not None else nullcontext()  # a grid's cap on concurrent LLM calls
        self.events = events
        self._stack = ExitStack()
        self._client: ChatClient | None = None

    def _get(self) -> ChatClient:
        if self._client is None:
            self._client = self._stack.enter_context(chat_client(self.config, self.events))
        return self._client

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        """``ChatClient.complete`` on the client started on first use, holding the run's LLM gate."""
        client = self._get()
        with self.gate:
            return client.complete(messages, D=D, seed=seed)

    def complete_document(self, prompt: str, *, D: int, seed: int | None = None, grammar: str | None = None,
                          temperature: float | None = None) -> Exchange:
        """Continue a document-form ``prompt`` (``ChatClient.complete_document``), starting the endpoint on first use."""
        client = self._get()
        with self.gate:
            return client.complete_document(prompt, D=D, seed=seed, grammar=grammar, temperature=temperature)

    def count_tokens(self, text: str) -> int:
        """A local estimate, nothing sent: one token per two characters (digit-heavy prompts tokenize
        densely; no tokenizer of the endpoint's model is known here). Every byte that leaves goes
        through the recording ``ChatClient``; R2PO refines this with the usage counts of its answers."""
        return len(text) // 2 + CHAT_TEMPLATE_MARGIN

    def close(self) -> None:
        """Close the client (and stop the embedded server) if one was started."""
        self._stack.close()


def start(
    config: RunConfig,
    run_dir: Path,
    events: RunEvents = RunEvents(),
    *,
    secrets: Secrets | None = None,
    llm_gate: AbstractContextManager[object] | None = None,
    chat: ChatModel | None = None,
) -> FinalEval | None:
    """Create the run directory (``create_run``) and run it (``execute``): warm-up, search, final
    evaluation, policy file (Algorithm 1 of the paper for the prompted methods).

    ``llm_gate`` (e.g. a shared semaphore) is held around every LLM request of the run; ``chat``
    replaces the configured LLM; ``secrets`` replaces freshly drawn ones (tests, controlled grids).

    Returns:
        The final evaluation (the best search policy on ``final_episodes`` fresh episodes, raw
        returns), or None when ``final_episodes`` is 0.

    Raises:
        ConfigError: an invalid config, or ``run_dir`` already holds something or cannot be made
            (nothing is written then).
        LLMError: the endpoint stayed down past the retries (the run is left resumable).
        KeyboardInterrupt: Ctrl-C; the run is marked ``interrupted`` and resumable.
        FeedbackKeyError, EpisodeLimitError: the env broke its declaration mid-run (status
            ``stopped: ...``).
    """
    store, secrets = create_run(config, run_dir, secrets)
    with store:
        stored = RunConfig.from_json(store.config())  # with the task's declaration
        return execute(run_dir, store, stored, secrets, events, llm_gate=llm_gate, chat=chat)


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


def change_endpoint(store: RunStore, config: RunConfig, endpoint: Endpoint) -> RunConfig:
    """The run's config with ``endpoint`` applied, validated, stored, and the change recorded.

    The store's config gets the new ``llm.base_url``, ``model`` and ``api_key_env`` (so a later
    plain ``resume`` keeps them), and ``endpoint_changes`` gets one entry (when, after how many
    candidates and LLM calls, from, to). Secrets and key file are untouched. Raises ConfigError
    for settings ``LLMConfig.validate`` refuses; returns ``config`` unchanged if nothing differs.
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


def resume(
    run_dir: Path,
    events: RunEvents = RunEvents(),
    *,
    llm_gate: AbstractContextManager[object] | None = None,
    endpoint: Endpoint | None = None,
    chat: ChatModel | None = None,
) -> FinalEval | None:
    """Continue a run with its own secrets: every recorded candidate is kept, the rest is run,
    then the final evaluation. ``endpoint`` continues it against a corrected or different LLM
    endpoint (``change_endpoint``). Raises StoreError for a missing or foreign directory or key
    file, ConfigError for a bad endpoint, LLMError when the endpoint stays down."""
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    store, config, secrets = load_run(run_dir)
    with store:
        if endpoint is not None and endpoint.given:
            config = change_endpoint(store, config, endpoint)
        return execute(run_dir, store, config, secrets, events, llm_gate=llm_gate, chat=chat)
