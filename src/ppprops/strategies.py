"""The search phase of each method (``ppprops.methods.METHODS`` names the builder of each).

Every search is a uniform warm-up followed by one phase of ``config.iterations`` asks: the four
ProPS presets (and pp-hardened) are one LLM proposer with different mechanisms, R2PO is a
two-stage LLM proposer, and the black-box baselines replace the LLM with another proposer at the
same budget (warm-up + iterations evaluations). The loop (``ppprops.loop``) is the same for all.
A builder takes a ``SearchSetup`` and returns a ``Phase``; adding a search method means adding a
builder (here, or anywhere for ``methods.register_method``) and a ``Method`` naming it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from .client.codec import Codec
from .config import RunConfig
from .errors import ConfigError
from .loop import Phase
from .methods import Method
from .proposers.base import Proposal, Proposer
from .proposers.uniform import UniformSampler
from .store import RunStore
from .tasks.base import Task
from .values import Candidate

if TYPE_CHECKING:
    from .evaluation import Evaluator


@dataclass(frozen=True)
class SearchSetup:
    """What a phase builder may use: the run's task, settings, codec, episode runner and store.

    ``chat`` returns the run's LLM client (started on its first request, closed by the runner);
    it is None for methods that send no prompt.
    """

    task: Task
    config: RunConfig
    codec: Codec
    evaluator: Evaluator
    store: RunStore
    chat: Callable[[], Any] | None = None


def search_phase(method: Method, setup: SearchSetup) -> Phase:
    """The phase that follows the warm-up (``setup.config.iterations`` asks) for ``method``.

    ``method.phase`` names a builder of this module or is the builder itself. Raises ConfigError
    for a method without one (an RL baseline).
    """
    if method.phase is None:
        raise ConfigError(f"{method.name} is an RL baseline; it has no search phase")
    build = globals()[method.phase] if isinstance(method.phase, str) else method.phase
    return build(setup)  # type: ignore[no-any-return]


class RandomSearch:
    """Uniform samples that continue the warm-up's stream: sample warmup + i, i.i.d. like the rest."""

    def __init__(self, D: int, box: tuple[float, float], seed: int, *, offset: int) -> None:
        self._uniform = UniformSampler(D, box, seed, source="random")
        self.offset = offset

    def ask(self, iteration: int) -> Proposal:
        """Sample ``offset + iteration`` of the warm-up's uniform stream (shape (D,), in the box)."""
        return self._uniform.ask(self.offset + iteration)

    def tell(self, candidate: Candidate) -> None:
        """Nothing: random search does not learn."""


def _llm_common(s: SearchSetup) -> dict[str, Any]:
    from .client.context import prompt_context

    assert s.chat is not None, "a prompted method needs the run's LLM client"
    store = s.store
    return dict(
        chat=s.chat(),
        codec=s.codec,
        context=prompt_context(s.task, s.config, s.codec),
        top_k=s.config.top_k,
        box=s.config.box,
        seed=s.config.seed,
        parse_retries=s.config.parse_retries,
        on_exchange=lambda it, att, ex, err: store.add_llm_call(it, att, ex, err),
    )


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


def props_phase(s: SearchSetup) -> Phase:
    """ProPS (Algorithm 1): one LLM call per iteration over the top-K history, under the run's
    mechanisms, in the run's prompt form (``prompt_form``: the document form for the embedded model)."""
    from .proposers import LLMProposer

    common = _llm_common(s)
    proposer = LLMProposer(on_llm_failure=s.config.on_llm_failure, form=prompt_form(s.config, common["chat"]),
                           temperature=s.config.llm.temperature, **common)
    return Phase("llm", proposer, s.config.iterations)


def r2po_phase(s: SearchSetup) -> Phase:
    """R2PO: a Search-LLM proposal, then a Critic-LLM revision from rollout evidence (two calls per iteration)."""
    from .llm.client import default_max_tokens
    from .proposers.r2po import R2POProposer
    from .rollout import record_rollout

    common = _llm_common(s)
    task, evaluator, config = s.task, s.evaluator, s.config
    proposer = R2POProposer(
        rollout=lambda theta, seed: record_rollout(task, evaluator.env, theta, seed),
        count_tokens=common["chat"].count_tokens,
        context_window=config.llm.context_size,
        max_tokens=config.llm.max_tokens or default_max_tokens(task.D),
        **common,
    )
    return Phase("r2po", proposer, config.iterations)


def random_phase(s: SearchSetup) -> Phase:
    """Random search: the uniform warm-up stream, continued for the LLM's budget."""
    proposer: Proposer = RandomSearch(s.task.D, s.config.box, s.config.seed, offset=s.config.warmup)
    return Phase("random", proposer, s.config.iterations)


def cmaes_phase(s: SearchSetup) -> Phase:
    """CMA-ES from the best warm-up policy, in the raw box or (``--encode-params on``) the encoded space."""
    from .proposers.cmaes import CMAESProposer

    proposer = CMAESProposer(D=s.task.D, box=s.config.box, seed=s.config.seed, codec=s.codec,
                             space="encoded" if s.config.mechanisms.encode_params else "raw")  # fmt: skip
    return Phase("cmaes", proposer, s.config.iterations)
