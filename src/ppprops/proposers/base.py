"""The ask/tell protocol every proposer implements, how a proposer stops a search, and what a
method's phase builder is given to build its proposer (``SearchSetup``) and returns (``Phase``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from ..client.codec import Codec
    from ..client.context import PromptSettings
    from ..evaluation import Evaluator
    from ..llm.recording import RecordingLLM
    from ..llm.settings import LLMConfig
    from ..seeding import Streams
    from ..tasks.base import Task
    from ..values import Candidate


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
    """The ask/tell interface of every search (warm-up sampler, LLM, R2PO, random, CMA-ES).

    ``ask`` may raise StopSearch to end the run on purpose; the study (``ppprops.study.Study``)
    evaluates and records each proposal and tells every proposer every candidate, in trial order,
    up to the first trial still out (so a proposer's state is the same in every process).

    With ``--parallel`` P > 1 a proposer may also have (all optional, looked up with ``getattr``):
    ``rounds = True`` (its P proposals of a round share what it was told when the round began; the
    study starts a round only when the last one is told: the LLM proposer), ``ask_many(iterations)``
    (a round's proposals at once, e.g. concurrent requests; default: one ``ask`` each),
    ``ready(iteration)`` (False while that iteration must wait for trials out: CMA-ES's next
    generation) and ``failed(trial)`` (a trial of the run failed and will never be told: CMA-ES
    counts it as the worst member). A failed trial is never told as a candidate.
    """

    def ask(self, iteration: int) -> Proposal:
        """The next candidate. ``iteration`` counts this proposer's own asks from 0, so a
        resumed run asks again for exactly the iteration that was interrupted."""
        ...

    def tell(self, candidate: Candidate) -> None:
        """Every evaluated candidate of the run, in order (including other proposers')."""
        ...


Bounds = tuple[float, float] | tuple[np.ndarray, np.ndarray]  # one (low, high) for every parameter, or one per parameter


def clip_to_box(theta: np.ndarray, box: Bounds) -> tuple[np.ndarray, int]:
    """``theta`` (shape (D,)) clipped into ``box`` = (low, high) (two numbers, or two arrays of shape
    (D,): an MLP's layer boxes), and how many coordinates were outside."""
    lo, hi = box
    clipped = int(np.count_nonzero((theta < lo) | (theta > hi)))
    return np.clip(theta, lo, hi), clipped


@dataclass(frozen=True)
class Phase:
    """A stretch of a search: ``budget`` candidates, each asked of ``proposer`` (warm-up, then the search).

    ``name`` labels it (``warmup``, ``llm``, ``r2po``, ``random``, ``cmaes``); ``budget`` >= 0.
    """

    name: str
    proposer: Proposer
    budget: int


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
