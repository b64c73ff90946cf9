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
import json
import math
import os
import shutil
import urllib.request
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, ExitStack, closing, contextmanager, nullcontext
from contextvars import ContextVar
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from . import seeding
from .client.context import prompt_context
from .client.hardening import codec_for, generate_secrets
from .client.secrets import Secrets
from .config import RunConfig
from .errors import ConfigError, LLMError, StoreError
from .evaluation import EpisodeLimitError, Evaluator, Feedback, WorkerError, check_parallel
from .llm.client import ChatClient, Exchange, default_max_tokens
from .loop import Phase, StopSearch, best_candidate, run_loop
from .policy_file import policy_document, write_json_atomic
from .proposers import LLMProposer
from .proposers.r2po import R2POProposer
from .proposers.uniform import warmup_sampler
from .rollout import record_rollout
from .store import DB_NAME, Candidate, FinalEval, RunStore, open_store
from .strategies import BLACK_BOX, black_box_phase
from .tasks import FeedbackKeyError, Task

KEY_NAME = "secrets.key"
# Errors of an env that breaks its task's declaration mid-run: the run stops (not resumable as is).
BROKEN_TASK = (FeedbackKeyError, EpisodeLimitError, WorkerError)
CHAT_TEMPLATE_MARGIN = 32  # tokens the chat template adds around a single user message
POLICY_NAME = "best_policy.json"


@dataclass(frozen=True)
class RunEvents:
    """Hooks for progress display; the runner itself prints nothing."""

    on_start: Callable[[int, int], None] = lambda done, total: None
    on_candidate: Callable[[Candidate, float | None, float], None] = lambda c, latency, best: None
    on_final: Callable[[FinalEval], None] = lambda fe: None


class ChatModel(Protocol):
    """What the runner asks an LLM through: the recording ``ChatClient`` or any object like it.

    ``complete`` sends one prompt (``messages``: OpenAI chat messages) for a vector of ``D`` numbers
    and returns the ``Exchange`` (request and answer text, recorded in the store, so the audit
    sees it); ``count_tokens`` measures a prompt (R2PO's context check); ``close`` ends it. A model
    that also has ``complete_document(prompt, *, D, seed, grammar)`` (``ChatClient`` does) can be
    sent the document form; without it, ``--prompt-form auto`` uses the chat form.
    """

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange: ...

    def count_tokens(self, text: str) -> int: ...

    def close(self) -> None: ...


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


def prompt_form(config: RunConfig, chat: object) -> str:
    """The form the run's proposer uses: ``config.form``, except that ``auto`` falls back to chat for
    a chat model that cannot continue documents. ``--prompt-form document`` with such a model is a
    ConfigError."""
    form = config.form
    if form == "document" and not callable(getattr(chat, "complete_document", None)):
        if config.prompt_form == "document":
            raise ConfigError("--prompt-form document needs a chat model with complete_document(prompt, *, D, seed, "
                              "grammar); this one has only complete(): use --prompt-form chat or auto")
        return "chat"
    return form


def new_run_id(config: RunConfig) -> str:
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
        store = RunStore(tmp / DB_NAME)
        try:
            store.init_run(run_id, config.to_json(), secrets.fingerprint())
        finally:
            store.close()  # the last connection checkpoints the WAL, so the directory can move
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
    store = open_store(run_dir)
    config = RunConfig.from_json(store.config())
    task = config.make_task()
    secrets = Secrets.load(Path(run_dir) / KEY_NAME, run_id=store.run_id(), D=task.D, fingerprint=store.key_fingerprint())
    return store, config, secrets


@contextmanager
def chat_client(config: RunConfig) -> Iterator[ChatClient]:
    """The configured endpoint, or the embedded llama.cpp server started for the duration."""
    llm = config.llm
    with ExitStack() as stack:
        if llm.embedded:
            from .llm.embedded import MODEL_ALIAS, EmbeddedServer

            server = stack.enter_context(EmbeddedServer(context_size=llm.context_size))
            client = ChatClient(llm, base_url=server.base_url, model=MODEL_ALIAS, api_key="not-needed", grammar_ok=True)
        else:
            api_key = "not-needed"
            if llm.api_key_env:
                api_key = os.environ.get(llm.api_key_env, "")
                if not api_key:
                    raise ConfigError(f"--api-key-env names {llm.api_key_env}, but that environment variable is empty or unset")
            assert llm.base_url is not None and llm.model is not None
            client = ChatClient(llm, base_url=llm.base_url, model=llm.model, api_key=api_key, grammar_ok=False)
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

    ``chat`` replaces the configured LLM (the caller keeps and closes it). An env that turns out
    to break its declaration mid-run (an info key gone, an episode that never ends) stops the run
    cleanly (status ``stopped: ...``) and raises that one-line error.
    """
    task = config.make_task()
    codec = codec_for(secrets, task, config)  # every mechanism of the config, hardening included
    done = store.candidates()
    total = config.warmup + config.iterations
    events.on_start(len(done), total)
    status = store.status()
    if not status.startswith("stopped"):
        status = "finished"
    elif len(done) < total:
        total = len(done)  # a run stopped on purpose (e.g. context overflow) is not continued
    with Evaluator(task, workers=config.workers) as evaluator, ExitStack() as stack:

        def evaluate(theta: np.ndarray, index: int) -> tuple[Feedback, Sequence[int]]:
            seeds = seeding.episode_seeds(config.seed, index, config.episodes)
            return evaluator.evaluate(theta, seeds), seeds

        if len(done) < total:
            warmup = warmup_sampler(task.D, config, codec)  # the paper's raw box, or an encoded one (hardened)
            phases = [Phase("warmup", warmup, config.warmup)]
            proposer: LLMProposer | None = None
            if config.iterations > 0 and config.method in BLACK_BOX:
                phases.append(black_box_phase(task, config, codec))
            elif config.iterations > 0:
                if chat is None:
                    factory = _CHAT_FACTORY.get()
                    chat = stack.enter_context(closing(factory(config) if factory is not None else LazyChat(config, llm_gate)))
                common = dict(
                    chat=chat,
                    codec=codec,
                    context=prompt_context(task, config, codec),
                    top_k=config.top_k,
                    box=config.box,
                    seed=config.seed,
                    parse_retries=config.parse_retries,
                    on_exchange=lambda it, att, ex, err: store.add_llm_call(it, att, ex, err),
                )
                if config.method == "r2po":
                    r2po = R2POProposer(
                        rollout=lambda theta, seed: record_rollout(task, evaluator.env, theta, seed),
                        count_tokens=chat.count_tokens,
                        context_window=config.llm.context_size,
                        max_tokens=config.llm.max_tokens or default_max_tokens(task.D),
                        **common,  # type: ignore[arg-type]
                    )
                    proposer = r2po  # type: ignore[assignment]
                    phases.append(Phase("r2po", r2po, config.iterations))
                else:
                    proposer = LLMProposer(on_llm_failure=config.on_llm_failure, form=prompt_form(config, chat),
                                           temperature=config.llm.temperature, **common)  # type: ignore[arg-type]
                    phases.append(Phase("llm", proposer, config.iterations))
            best_so_far = [max((c.ret for c in done if math.isfinite(c.ret)), default=-np.inf)]

            def on_candidate(c: Candidate) -> None:
                if math.isfinite(c.ret):  # a numerical fault is never the best so far
                    best_so_far[0] = max(best_so_far[0], c.ret)
                latency = proposer.last_latency if (proposer is not None and c.source != "warmup") else None
                events.on_candidate(c, latency, best_so_far[0])

            try:
                done = run_loop(phases, evaluate=evaluate, codec=codec, store=store, done=done, on_candidate=on_candidate)
            except StopSearch as stop:
                done = store.candidates()
                status = f"stopped: {stop.reason}"
            except LLMError as e:  # the endpoint stayed down past the retry bound: stop, resumable
                raise LLMError(f"{e}; the run is saved: continue with 'ppprops resume {run_dir}'") from e
            except BROKEN_TASK as e:  # the env broke its declaration
                store.set_status(f"stopped: {e}")
                raise
        try:
            fe = finish(run_dir, store, config, task, evaluator, done, status=status)
        except BROKEN_TASK as e:
            store.set_status(f"stopped: {e}")
            raise
    events.on_final(fe) if fe is not None else None
    return fe


def finish(
    run_dir: Path, store: RunStore, config: RunConfig, task: Task, evaluator: Evaluator, done: list[Candidate],
    *, status: str = "finished",
) -> FinalEval | None:
    best = best_candidate(done)
    fe = store.final_eval()
    if fe is None or fe.candidate_index != best.index:
        seeds = seeding.final_eval_seeds(config.seed, config.final_episodes)
        returns = evaluator.evaluate(best.params, seeds).episode_returns if seeds else ()
        fe = FinalEval(candidate_index=best.index, returns=tuple(returns), seeds=tuple(seeds))
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
    store.set_status(status)
    return fe


class LazyChat:
    """Starts the LLM only when the first LLM iteration asks, so warm-up never waits for it."""

    def __init__(self, config: RunConfig, gate: AbstractContextManager[object] | None = None) -> None:
        self.config = config
        self.gate = gate if gate is not None else nullcontext()  # a grid's cap on concurrent LLM calls
        self._stack = ExitStack()
        self._client: ChatClient | None = None

    def _get(self) -> ChatClient:
        if self._client is None:
            self._client = self._stack.enter_context(chat_client(self.config))
        return self._client

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        client = self._get()
        with self.gate:
            return client.complete(messages, D=D, seed=seed)

    def complete_document(self, prompt: str, *, D: int, seed: int | None = None, grammar: str | None = None,
                          temperature: float | None = None) -> Exchange:
        client = self._get()
        with self.gate:
            return client.complete_document(prompt, D=D, seed=seed, grammar=grammar, temperature=temperature)

    def count_tokens(self, text: str) -> int:
        """Exact with a llama.cpp server (its /tokenize endpoint); otherwise a conservative
        estimate of one token per two characters (digit-heavy prompts tokenize densely)."""
        client = self._get()
        root = str(client._client.base_url).rstrip("/").removesuffix("/v1")
        try:
            req = urllib.request.Request(root + "/tokenize", data=json.dumps({"content": text}).encode(),
                                         headers={"Content-Type": "application/json"}, method="POST")
            with urllib.request.urlopen(req, timeout=30) as resp:
                return len(json.loads(resp.read())["tokens"]) + CHAT_TEMPLATE_MARGIN
        except (OSError, ValueError, KeyError):
            return len(text) // 2 + CHAT_TEMPLATE_MARGIN

    def close(self) -> None:
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
    """Create the run directory and run it. ``llm_gate`` (e.g. a shared semaphore) is held around
    every LLM request of the run; ``chat`` replaces the configured LLM (see ``execute``)."""
    store, secrets = create_run(config, run_dir, secrets)
    try:
        stored = RunConfig.from_json(store.config())  # with the task's declaration
        return execute(run_dir, store, stored, secrets, events, llm_gate=llm_gate, chat=chat)
    finally:
        store.close()


def resume(
    run_dir: Path, events: RunEvents = RunEvents(), *, llm_gate: AbstractContextManager[object] | None = None,
    chat: ChatModel | None = None,
) -> FinalEval | None:
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    store, config, secrets = load_run(run_dir)
    try:
        return execute(run_dir, store, config, secrets, events, llm_gate=llm_gate, chat=chat)
    finally:
        store.close()
