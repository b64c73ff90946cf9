"""CMA-ES (pycma) as a proposer: an equal-budget black-box baseline for the LLM.

It starts after the same uniform warm-up as PP-ProPS: the mean is the best warm-up policy.
Two spaces:
- ``raw``: CMA-ES searches theta inside the public box (pycma's bound transform keeps every
  sample feasible), sigma0 = 0.3 x box width;
- ``encoded``: CMA-ES sees only what a provider would see, theta~ = A theta and c r, with no box
  (the per-coordinate range would reveal A). It takes per-coordinate step sizes from the spread
  of the encoded warm-up samples; the client decodes and clips its proposals.

Populations are generated deterministically from the run seed, so a resumed run regenerates
exactly the population it was in the middle of.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from ..client.codec import Codec
from ..errors import MissingExtraError
from ..values import Candidate, Trial
from .base import Bounds, Proposal, SearchProposer, clip_to_box

Space = Literal["raw", "encoded"]


class CMAESProposer(SearchProposer):
    """CMA-ES (pycma) at the prompted methods' budget, started from the best warm-up policy.

    ``space="raw"`` searches theta in the box (initial step 0.3 x box width); ``"encoded"`` searches
    theta~ = A theta with step 1 and decodes each sample (the optimizer then sees what the LLM sees).
    Raises MissingExtraError (extra ``baselines``) when pycma is not installed.
    """

    def __init__(self, *, D: int, box: Bounds, seed: int, codec: Codec, space: Space = "raw",
                 popsize: int | None = None, sigma0: float = 0.3, source: str = "cmaes") -> None:
        """``seed`` seeds pycma's sampling; ``popsize`` (None: pycma's 4 + 3 ln D) and ``sigma0``
        (initial step, share of the box width; the encoded space scales its unit step by
        ``sigma0 / 0.3``) are the method's options (``methods.CMAESOptions``)."""
        try:
            import cma  # noqa: F401
        except ImportError as e:
            raise MissingExtraError("baselines", "--method cmaes") from e
        self.D, self.box, self.seed, self.codec, self.space = D, box, seed, codec, space
        self.popsize = popsize
        self.sigma0 = sigma0
        self.source = source
        self._warmup: list[Candidate] = []
        self._es: Any = None  # cma.CMAEvolutionStrategy once started (pycma has no type information)
        self._pop: list[np.ndarray] | None = None
        self._fit: dict[int, float] = {}  # member -> fitness, as told (in any order)
        self._gen = 0  # the generation being asked and told

    def _start(self) -> None:
        import cma

        if not self._warmup:
            raise RuntimeError("CMA-ES starts from the warm-up; none was told")
        best = max(self._warmup, key=lambda c: c.ret)
        lo, hi = self.box
        opts: dict[str, object] = {"seed": int(self.seed % (2**31 - 1)) + 1, "verbose": -9}
        if self.popsize:
            opts["popsize"] = self.popsize
        if self.space == "raw":
            width = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
            if width.ndim:  # an MLP's layer boxes: one step per coordinate, sigma0 x its layer box's width
                opts["bounds"] = [np.asarray(lo).tolist(), np.asarray(hi).tolist()]
                opts["CMA_stds"] = (width / width.max()).tolist()
                self._es = cma.CMAEvolutionStrategy(np.asarray(best.params), self.sigma0 * float(width.max()), opts)
            else:
                opts["bounds"] = [lo, hi]
                self._es = cma.CMAEvolutionStrategy(np.asarray(best.params), self.sigma0 * (hi - lo), opts)
        else:
            spread = np.std([c.params_enc for c in self._warmup], axis=0)
            spread = np.where(spread > 0, spread, 1.0)
            opts["CMA_stds"] = spread.tolist()
            self._es = cma.CMAEvolutionStrategy(np.asarray(best.params_enc), self.sigma0 / 0.3, opts)

    def _population(self) -> list[np.ndarray]:
        if self._es is None:
            self._start()
        if self._pop is None:
            self._pop = [np.asarray(x, dtype=np.float64) for x in self._es.ask()]
            self._fit = {}
        return self._pop

    @property
    def _size(self) -> int:
        """The population size (pycma's, known once started)."""
        return len(self._population())

    def ready(self, iteration: int) -> bool:
        """True when ``iteration``'s population can be asked: every earlier generation is told
        (with ``--parallel`` P, a round never reaches into the next generation before that)."""
        return iteration // self._size <= self._gen

    def ask(self, iteration: int) -> Proposal:
        """Member ``iteration mod popsize`` of the current population, decoded if needed and clipped into the box: shape (D,)."""
        x = self._population()[iteration % self._size]
        theta = x if self.space == "raw" else self.codec.decode(x)
        theta, clipped = clip_to_box(theta, self.box)
        return Proposal(theta=theta, source=self.source, clipped=clipped)

    def tell(self, candidate: Candidate) -> None:
        """Warm-up candidates seed the start; the population's own returns (negated: CMA-ES
        minimizes) feed ``tell`` once every member is told, in whatever order they came."""
        if candidate.source != self.source:
            self._warmup.append(candidate)
            return
        # pycma minimises; in the encoded space it only ever sees the scaled return
        ret = candidate.feedback.ret if self.space == "raw" else candidate.feedback_enc.ret
        self._member(candidate.iteration, -ret if np.isfinite(ret) else np.inf)

    def failed(self, trial: Trial) -> None:
        """A member whose trial failed counts as the worst (fitness +inf), so the generation goes on."""
        if trial.source == self.source:
            self._member(trial.iteration, np.inf)

    def _member(self, iteration: int, fitness: float) -> None:
        pop = self._population()
        if iteration // len(pop) != self._gen:
            return  # a member of a generation already told (a failed trial asked again): too late to count
        self._fit[iteration % len(pop)] = fitness
        if len(self._fit) == len(pop):
            self._es.tell(pop, [self._fit[m] for m in range(len(pop))])
            self._pop = None
            self._gen += 1
