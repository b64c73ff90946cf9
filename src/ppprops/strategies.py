"""Which proposers make up a run, per ``--method``.

The four ProPS presets (vanilla, pe, df, pp) are one LLM proposer with different mechanisms;
the black-box baselines replace the LLM phase with another proposer at the same budget
(warm-up + iterations evaluations). The loop is the same for all of them.
"""

from __future__ import annotations

from .client.codec import Codec
from .config import RunConfig
from .loop import Phase
from .proposers.base import Proposal, Proposer
from .proposers.uniform import UniformSampler
from .store import Candidate
from .tasks.base import Task

BLACK_BOX = ("random", "cmaes")


class RandomSearch:
    """Uniform samples that continue the warm-up's stream: sample warmup + i, i.i.d. like the rest."""

    def __init__(self, D: int, box: tuple[float, float], seed: int, *, offset: int) -> None:
        self._uniform = UniformSampler(D, box, seed, source="random")
        self.offset = offset

    def ask(self, iteration: int) -> Proposal:
        return self._uniform.ask(self.offset + iteration)

    def tell(self, candidate: Candidate) -> None:
        pass


def black_box_phase(task: Task, config: RunConfig, codec: Codec) -> Phase:
    """The search phase of a black-box baseline, after the shared uniform warm-up."""
    proposer: Proposer
    if config.method == "random":
        proposer = RandomSearch(task.D, config.box, config.seed, offset=config.warmup)
    elif config.method == "cmaes":
        from .proposers.cmaes import CMAESProposer

        space = "encoded" if config.mechanisms.encode_params else "raw"
        proposer = CMAESProposer(D=task.D, box=config.box, seed=config.seed, codec=codec, space=space)
    else:
        raise ValueError(f"{config.method} is not a black-box method")
    return Phase(config.method, proposer, config.iterations)
