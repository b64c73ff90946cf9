"""The ask/tell protocol every proposer implements, how a proposer stops a search, and what a
method's phase builder is given to build its proposer (``SearchSetup``) and returns (``Phase``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

if TYPE_CHECKING:
    from ..client.codec import Codec
    from ..client.context import PromptSettings
    from ..evaluation import Evaluator
    from ..llm.recording import RecordingLLM
    from ..llm.settings import LLMConfig
    from ..seeding import Streams
    from ..tasks.base import Task
    from ..values import Candidate, Trial


class StopSearch(Exception):
    """Raised by a proposer's ``ask`` when it cannot go on (e.g. its prompt no longer fits the
    context window). The run stops there (status ``stopped: <reason>``) and reports the best
    policy found before it; ``reason`` is that one line."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class Proposal:
    """One proposed policy: raw theta, shape (D,), inside the box, and where it came from."""

    theta: np.ndarray  # raw parameters, already inside the feasible box
    source: str  # recorded as the candidate's source: warmup, llm, fallback, random, ...
    clipped: int = 0  # coordinates that had to be clipped into the box
    note: str = ""
    seeds: tuple[int, ...] | None = None  # its own episode seeds (None: the run's, ``episodes`` of them)
    reevaluates: int | None = None  # the search candidate it runs again (the selection stage)


class Proposer(Protocol):
    """The ask/tell interface every search has (warm-up sampler, LLM, R2PO, random, CMA-ES, yours).

    ``ask`` may raise StopSearch to end the run on purpose; the study (``ppprops.study.Study``)
    evaluates and records each proposal and tells every proposer every candidate, in trial order,
    up to the first trial still out (so a proposer's state is the same in every process). A
    proposer with only these two methods is given ``SearchProposer``'s default hooks
    (``as_search_proposer``); subclass ``SearchProposer`` to have hooks of its own.
    """

    def ask(self, iteration: int) -> Proposal:
        """The next candidate. ``iteration`` counts this proposer's own asks from 0, so a
        resumed run asks again for exactly the iteration that was interrupted."""
        ...

    def tell(self, candidate: Candidate) -> None:
        """Every evaluated candidate of the run, in order (including other proposers')."""
        ...


class SearchProposer:
    """A proposer with every hook the study calls, each with its default (subclass it and override
    what your search needs; ``ask`` at least).

    The hooks matter with ``--parallel`` P > 1 and with failed trials: ``rounds`` (True: the P
    proposals of a round share what the proposer was told when the round began, and the study
    starts a round only when the last one is told: the LLM proposer), ``ask_many`` (a round's
    proposals at once, e.g. concurrent requests), ``ready`` (False while an iteration must wait for
    trials out: CMA-ES's next generation), ``failed`` (a trial of the run failed and will never be
    told: CMA-ES counts it as the worst member), ``latency`` (seconds of its latest LLM call, for the
    pacer). A failed trial is never told as a candidate.
    """

    rounds: ClassVar[bool] = False

    def ask(self, iteration: int) -> Proposal:
        """The next candidate (``Proposer.ask``). Raises StopSearch to end the run on purpose."""
        raise NotImplementedError(f"{type(self).__name__} has no ask")

    def tell(self, candidate: Candidate) -> None:
        """Every evaluated candidate of the run, in order (``Proposer.tell``); default: nothing."""

    def ask_many(self, iterations: Sequence[int]) -> list[Proposal]:
        """The proposals for ``iterations`` (one round); default: one ``ask`` each, in order."""
        return [self.ask(it) for it in iterations]

    def ready(self, iteration: int) -> bool:
        """False while ``iteration`` must wait for trials that are out; default: always ready."""
        return True

    def failed(self, trial: Trial) -> None:
        """Trial ``trial`` failed and will never be told; default: nothing."""

    def latency(self) -> float | None:
        """Seconds of this proposer's latest LLM call (None: none yet, or it sends none)."""
        return None


class _AskTell(SearchProposer):
    """A proposer with only ``ask`` and ``tell`` (``Proposer``), given ``SearchProposer``'s defaults."""

    def __init__(self, proposer: Proposer) -> None:
        self.proposer = proposer

    def ask(self, iteration: int) -> Proposal:
        """The wrapped proposer's ``ask``."""
        return self.proposer.ask(iteration)

    def tell(self, candidate: Candidate) -> None:
        """The wrapped proposer's ``tell``."""
        self.proposer.tell(candidate)

    def __repr__(self) -> str:
        return repr(self.proposer)


def as_search_proposer(proposer: Proposer | SearchProposer) -> SearchProposer:
    """``proposer`` itself when it is a ``SearchProposer``, else ``proposer`` behind an adapter with
    the default hooks (a user's ask/tell proposer: ``SearchProposer``)."""
    return proposer if isinstance(proposer, SearchProposer) else _AskTell(proposer)


Bounds = tuple[float, float] | tuple[np.ndarray, np.ndarray]  # one (low, high) for every parameter, or one per parameter


def clip_to_box(theta: np.ndarray, box: Bounds) -> tuple[np.ndarray, int]:
    """``theta`` (shape (D,)) clipped into ``box`` = (low, high) (two numbers, or two arrays of shape
    (D,): an MLP's layer boxes), and how many coordinates were outside."""
    lo, hi = box
    clipped = int(np.count_nonzero((theta < lo) | (theta > hi)))
    return np.clip(theta, lo, hi), clipped


@dataclass(frozen=True, init=False)
class Phase:
    """A stretch of a search: ``budget`` candidates, each asked of ``proposer`` (warm-up, then the search).

    ``name`` labels it (``warmup``, ``llm``, ``r2po``, ``random``, ``cmaes``); ``budget`` >= 0.
    ``proposer`` is a ``SearchProposer``, or any ask/tell ``Proposer``, which the phase keeps behind
    the default hooks (``as_search_proposer``). ``offset``: the proposer's iteration at the phase's
    first trial (0; more for the rest of a search continued after its selection stage,
    ``phases.plan_phases``): the phase asks iterations ``offset`` to ``offset + budget - 1``.
    """

    name: str
    proposer: SearchProposer
    budget: int
    offset: int

    def __init__(self, name: str, proposer: Proposer | SearchProposer, budget: int, offset: int = 0) -> None:
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "proposer", as_search_proposer(proposer))
        object.__setattr__(self, "budget", budget)
        object.__setattr__(self, "offset", offset)


@dataclass(frozen=True)
class SearchSetup:
    """What a method's phase builder is given: the narrow pieces of a run it may use, never the
    whole run config.

    ``task`` (D, the public task facts), ``codec`` (the only producer of encoded values),
    ``streams`` (the run's keyed random streams), ``box`` (the public raw range of every
    parameter; ``bounds`` narrows it per layer for an MLP), ``warmup`` and ``iterations`` (the budget before and of the search phase),
    ``prompt`` (how prompts are written, the resolved form included), ``llm`` (the endpoint's
    settings: context window, token budget, temperature), ``options`` (the method's own options,
    ``Method.parse_options``: a pydantic model or None), ``on_llm_failure`` and
    ``parse_retries``. ``llm_client()`` returns the run's recording LLM client
    (``llm.recording.RecordingLLM``; its model is started on the first request and closed by the
    study; None for methods that send no prompt); ``evaluator`` runs episodes of the
    task's env (R2PO's rollouts; None for a task without an env).
    """

    task: Task
    codec: Codec
    streams: Streams
    box: tuple[float, float]
    warmup: int
    iterations: int
    prompt: PromptSettings
    llm: LLMConfig
    options: Any = None
    on_llm_failure: str = "stop"
    parse_retries: int = 2
    llm_client: Callable[[], RecordingLLM] | None = None
    evaluator: Evaluator | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def bounds(self) -> Bounds:
        """Where the proposers keep theta: ``box`` itself for the linear policy (the paper's), the
        per-layer boxes of an MLP (``PolicySpec.bounds``: two arrays of shape (D,)) otherwise."""
        policy = self.task.policy
        return self.box if policy.is_linear else policy.bounds(self.task.n_s, self.task.n_a, self.box)

    @property
    def init_bounds(self) -> Bounds:
        """Where the warm-up draws (and random search continues it): ``box`` for the linear policy,
        the scaled initialisation of an MLP's layers (``PolicySpec.init_bounds``) otherwise."""
        policy = self.task.policy
        return self.box if policy.is_linear else policy.init_bounds(self.task.n_s, self.task.n_a, self.box)
