"""The search phase of each method (``ppprops.methods.METHODS`` names the builder of each).

Every search is a uniform warm-up followed by one phase of ``iterations`` asks: the four ProPS
presets (and pp-hardened) are one LLM proposer with different mechanisms, R2PO is a two-stage
LLM proposer, and the black-box baselines replace the LLM with another proposer at the same
budget (warm-up + iterations evaluations). The study (``ppprops.study``) asks them all the same
way. A builder takes a ``proposers.base.SearchSetup`` (narrow pieces of the run, never its whole
config) and returns a ``proposers.base.Phase``; adding a search method means adding a builder
(here, or anywhere for ``methods.register_method``) and a ``Method`` naming it.
"""

from __future__ import annotations

from .client.context import prompt_context
from .errors import ConfigError
from .methods import Method
from .proposers.base import Bounds, Phase, Proposal, SearchProposer, SearchSetup
from .proposers.llm import LLMSearch
from .proposers.uniform import UniformSampler
from .seeding import Streams
from .values import Candidate

__all__ = ["Phase", "SearchSetup", "cmaes_phase", "props_phase", "r2po_phase", "random_phase", "search_phase"]


def search_phase(method: Method, setup: SearchSetup) -> Phase:
    """The phase that follows the warm-up (``setup.iterations`` asks) for ``method``.

    ``method.phase`` names a builder of this module or is the builder itself. Raises ConfigError
    for a method without one (an RL baseline).
    """
    if method.phase is None:
        raise ConfigError(f"{method.name} is an RL baseline; it has no search phase")
    build = globals()[method.phase] if isinstance(method.phase, str) else method.phase
    return build(setup)  # type: ignore[no-any-return]


class RandomSearch(SearchProposer):
    """Uniform samples that continue the warm-up's stream: sample warmup + i, i.i.d. like the rest."""

    def __init__(self, D: int, box: Bounds, streams: Streams, *, offset: int) -> None:
        self._uniform = UniformSampler(D, box, streams, source="random")
        self.offset = offset

    def ask(self, iteration: int) -> Proposal:
        """Sample ``offset + iteration`` of the warm-up's uniform stream (shape (D,), in the box)."""
        return self._uniform.ask(self.offset + iteration)

    def tell(self, candidate: Candidate) -> None:
        """Nothing: random search does not learn."""


def llm_search(s: SearchSetup) -> LLMSearch:
    """What the run's LLM proposers share: its recording client, codec, prompt context and settings."""
    assert s.llm_client is not None, "a prompted method needs the run's LLM client"
    return LLMSearch(llm=s.llm_client(), codec=s.codec, context=prompt_context(s.task, s.prompt, s.codec), top_k=s.prompt.top_k,
                     box=s.bounds, streams=s.streams, parse_retries=s.parse_retries, on_llm_failure=s.on_llm_failure,
                     temperature=s.llm.temperature, explore=s.prompt.explore)  # fmt: skip


def props_phase(s: SearchSetup) -> Phase:
    """ProPS (Algorithm 1): one LLM call per iteration over the top-K history, under the run's
    mechanisms, in the run's prompt form (``s.prompt.form``: the document form for the embedded model)."""
    from .proposers import LLMProposer
    from .wire.forms import FORMS

    return Phase("llm", LLMProposer(llm_search(s), form=FORMS[s.prompt.form]), s.iterations)


def r2po_phase(s: SearchSetup) -> Phase:
    """R2PO: a Search-LLM proposal, then a Critic-LLM revision from rollout evidence (two calls per iteration)."""
    from .llm.client import default_max_tokens
    from .proposers.r2po import R2POProposer
    from .rollout import record_rollout

    if not s.task.policy.is_linear:
        raise ConfigError(f"--method r2po searches the linear policy only (its critic reads a linear rollout): "
                          f"--policy {s.task.policy.label().split()[0]} needs --method pp, random or cmaes")
    if s.evaluator is None:
        raise ConfigError(f"--method r2po re-runs episodes for its critic: task {s.task.name} has no env to run them in")
    task, evaluator = s.task, s.evaluator
    proposer = R2POProposer(llm_search(s), rollout=lambda theta, seed: record_rollout(task, evaluator.env, theta, seed),
                            context_window=s.llm.context_size, max_tokens=s.llm.max_tokens or default_max_tokens(task.D))
    return Phase("r2po", proposer, s.iterations)


def random_phase(s: SearchSetup) -> Phase:
    """Random search: the uniform warm-up stream, continued for the LLM's budget (an MLP's: its scaled
    initialisation, ``SearchSetup.init_bounds``)."""
    proposer = RandomSearch(s.task.D, s.init_bounds, s.streams, offset=s.warmup)
    return Phase("random", proposer, s.iterations)


def cmaes_phase(s: SearchSetup) -> Phase:
    """CMA-ES from the best warm-up policy, in the raw box or (``--encode-params on``) the encoded
    space; ``--method-options`` sets its ``popsize`` and ``sigma0`` (``methods.CMAESOptions``)."""
    from . import seeding
    from .proposers.cmaes import CMAESProposer

    popsize = getattr(s.options, "popsize", None)
    sigma0 = getattr(s.options, "sigma0", 0.3)
    seed = s.streams.int_seed(seeding.OPTIMIZER) if s.streams.keyed else s.streams.seed
    proposer = CMAESProposer(D=s.task.D, box=s.bounds, seed=seed, codec=s.codec, popsize=popsize, sigma0=sigma0,
                             space="encoded" if s.prompt.mechanisms.encode_params else "raw")  # fmt: skip
    return Phase("cmaes", proposer, s.iterations)

