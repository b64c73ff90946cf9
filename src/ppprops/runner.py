"""Starting, resuming and finishing a run directory: the client-side orchestration.

A run directory holds ``run.sqlite`` (the store), ``secrets.key`` (mode 0600) and, once
finished, ``best_policy.json``.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import seeding
from .client.codec import Codec
from .client.context import prompt_context
from .client.secrets import Secrets
from .config import RunConfig
from .errors import ConfigError, StoreError
from .evaluation import Evaluator, Feedback
from .llm.client import ChatClient, Exchange
from .loop import Phase, best_candidate, run_loop
from .policy_file import policy_document, write_json_atomic
from .proposers import LLMProposer, UniformSampler
from .strategies import BLACK_BOX, black_box_phase
from .store import DB_NAME, Candidate, FinalEval, RunStore, open_store
from .tasks import Task, get_task

KEY_NAME = "secrets.key"
POLICY_NAME = "best_policy.json"


@dataclass(frozen=True)
class RunEvents:
    """Hooks for progress display; the runner itself prints nothing."""

    on_start: Callable[[int, int], None] = lambda done, total: None
    on_candidate: Callable[[Candidate, float | None, float], None] = lambda c, latency, best: None
    on_final: Callable[[FinalEval], None] = lambda fe: None


def new_run_id(config: RunConfig) -> str:
    return f"{config.task}__{config.method}__{config.seed}__{uuid.uuid4().hex[:8]}"


def create_run(config: RunConfig, run_dir: Path, secrets: Secrets | None = None) -> tuple[RunStore, Secrets]:
    """Make the directory, key file and store. Refuses a directory that already holds something.

    ``secrets`` is for tests and controlled experiments; normally they are drawn fresh here.
    """
    config.validate()
    task = get_task(config.task)
    run_dir = Path(run_dir)
    if run_dir.exists() and any(run_dir.iterdir()):
        what = "another run" if (run_dir / DB_NAME).exists() else "files"
        raise ConfigError(f"output directory {run_dir} already holds {what}; choose a new --out or use 'ppprops resume'")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot create output directory {run_dir}: {e.strerror}") from None
    run_id = new_run_id(config) if secrets is None else secrets.run_id
    if secrets is None:
        secrets = Secrets.generate(run_id, task.D)
    elif len(secrets.a) != task.D:
        raise ConfigError(f"given secrets have D={len(secrets.a)}, task {task.name} needs {task.D}")
    secrets.save(run_dir / KEY_NAME)
    store = open_store(run_dir, create=True)
    store.init_run(run_id, config.to_json(), secrets.fingerprint())
    return store, secrets


def load_run(run_dir: Path) -> tuple[RunStore, RunConfig, Secrets]:
    store = open_store(run_dir)
    config = RunConfig.from_json(store.config())
    task = get_task(config.task)
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


def execute(run_dir: Path, store: RunStore, config: RunConfig, secrets: Secrets, events: RunEvents = RunEvents()) -> FinalEval | None:
    """Run (or continue) the search, then the final evaluation, then write the policy file."""
    task = get_task(config.task)
    codec = Codec(secrets, encode_params=config.mechanisms.encode_params, scale_rewards=config.mechanisms.scale_rewards)
    done = store.candidates()
    total = config.warmup + config.iterations
    events.on_start(len(done), total)
    with Evaluator(task) as evaluator, ExitStack() as stack:

        def evaluate(theta: np.ndarray, index: int) -> tuple[Feedback, Sequence[int]]:
            seeds = seeding.episode_seeds(config.seed, index, config.episodes)
            return evaluator.evaluate(theta, seeds), seeds

        if len(done) < total:
            warmup = UniformSampler(task.D, config.box, config.seed)
            phases = [Phase("warmup", warmup, config.warmup)]
            proposer: LLMProposer | None = None
            if config.iterations > 0 and config.method in BLACK_BOX:
                phases.append(black_box_phase(task, config, codec))
            elif config.iterations > 0:
                chat = stack.enter_context(closing(LazyChat(config)))
                proposer = LLMProposer(
                    chat=chat,
                    codec=codec,
                    context=prompt_context(task, config, codec),
                    top_k=config.top_k,
                    box=config.box,
                    seed=config.seed,
                    parse_retries=config.parse_retries,
                    on_exchange=lambda it, att, ex, err: store.add_llm_call(it, att, ex, err),
                )
                phases.append(Phase("llm", proposer, config.iterations))
            best_so_far = [max((c.ret for c in done), default=-np.inf)]

            def on_candidate(c: Candidate) -> None:
                best_so_far[0] = max(best_so_far[0], c.ret)
                latency = proposer.last_latency if (proposer is not None and c.source != "warmup") else None
                events.on_candidate(c, latency, best_so_far[0])

            done = run_loop(phases, evaluate=evaluate, codec=codec, store=store, done=done, on_candidate=on_candidate)
        fe = finish(run_dir, store, config, task, evaluator, done)
    events.on_final(fe) if fe is not None else None
    return fe


def finish(run_dir: Path, store: RunStore, config: RunConfig, task: Task, evaluator: Evaluator, done: list[Candidate]) -> FinalEval | None:
    best = best_candidate(done)
    fe = store.final_eval()
    if fe is None or fe.candidate_index != best.index:
        seeds = seeding.final_eval_seeds(config.seed, config.final_episodes)
        returns = evaluator.evaluate(best.params, seeds).episode_returns if seeds else ()
        fe = FinalEval(candidate_index=best.index, returns=tuple(returns), seeds=tuple(seeds))
        store.set_final_eval(fe)
    final = {"mean": fe.mean, "std": fe.std, "episodes": len(fe.returns), "seed": config.seed} if fe.returns else None
    search = {"run_id": store.run_id(), "method": config.method, "seed": config.seed, "return": best.ret, "candidate": best.index}
    write_json_atomic(Path(run_dir) / POLICY_NAME, policy_document(task, best.params, search=search, final_eval=final))
    store.set_status("finished")
    return fe


class LazyChat:
    """Starts the LLM only when the first LLM iteration asks, so warm-up never waits for it."""

    def __init__(self, config: RunConfig) -> None:
        self.config = config
        self._stack = ExitStack()
        self._client: ChatClient | None = None

    def _get(self) -> ChatClient:
        if self._client is None:
            self._client = self._stack.enter_context(chat_client(self.config))
        return self._client

    def complete(self, messages: list[dict[str, str]], *, D: int, seed: int | None = None) -> Exchange:
        return self._get().complete(messages, D=D, seed=seed)

    def close(self) -> None:
        self._stack.close()


def start(
    config: RunConfig, run_dir: Path, events: RunEvents = RunEvents(), *, secrets: Secrets | None = None
) -> FinalEval | None:
    store, secrets = create_run(config, run_dir, secrets)
    try:
        return execute(run_dir, store, config, secrets, events)
    finally:
        store.close()


def resume(run_dir: Path, events: RunEvents = RunEvents()) -> FinalEval | None:
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    store, config, secrets = load_run(run_dir)
    try:
        return execute(run_dir, store, config, secrets, events)
    finally:
        store.close()
