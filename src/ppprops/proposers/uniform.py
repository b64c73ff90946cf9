"""Uniform samples from the feasible box: the warm-up of Algorithm 1 (and random search)."""

from __future__ import annotations

import numpy as np

from .. import seeding
from ..store import Candidate
from .base import Proposal


class UniformSampler:
    def __init__(self, D: int, box: tuple[float, float], seed: int, *, source: str = "warmup") -> None:
        self.D = D
        self.box = box
        self.seed = seed
        self.source = source

    def ask(self, iteration: int) -> Proposal:
        # One stream per sample, so sample m is the same whether or not the run was interrupted.
        lo, hi = self.box
        theta = seeding.rng(self.seed, seeding.WARMUP, iteration).uniform(lo, hi, size=self.D)
        return Proposal(theta=theta, source=self.source)

    def tell(self, candidate: Candidate) -> None:
        pass
