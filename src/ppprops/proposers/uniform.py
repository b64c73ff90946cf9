"""Uniform samples from the feasible box: the warm-up of Algorithm 1 (and random search).

The paper samples raw parameters uniformly from the public box; their encoded spread then states
each a_j (max |theta~_j| / 6). The hardened warm-up (``encoded_warmup``) draws uniformly from a
public *encoded* box instead and decodes, so what the provider sees has the same distribution
whatever the secrets are.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from .. import seeding
from ..values import Candidate
from .base import Proposal

if TYPE_CHECKING:
    from ..client.codec import Codec
    from ..client.mechanisms import Mechanisms

Decode = Callable[[np.ndarray], np.ndarray]


class UniformSampler:
    """Uniform samples in ``box``, shape (D,) each; sample m comes from its own seeded stream (the
    same whether or not the run was interrupted). The paper's warm-up (Algorithm 1, line 1).
    """

    def __init__(
        self, D: int, box: tuple[float, float], streams: seeding.Streams, *, source: str = "warmup", decode: Decode | None = None
    ) -> None:
        """``streams``: the run's random streams (sample m is draw m of ``seeding.WARMUP``).
        ``decode`` given: ``box`` is a box of the encoded space and samples are decoded to raw ones."""
        self.D = D
        self.box = box
        self.streams = streams
        self.source = source
        self.decode = decode

    def ask(self, iteration: int) -> Proposal:
        # One stream per sample, so sample m is the same whether or not the run was interrupted.
        """Sample ``iteration`` of the stream (decoded to raw theta when ``decode`` is given)."""
        lo, hi = self.box
        theta = self.streams.rng(seeding.WARMUP, iteration).uniform(lo, hi, size=self.D)
        if self.decode is not None:
            theta = np.asarray(self.decode(theta), dtype=np.float64)
        return Proposal(theta=theta, source=self.source)

    def tell(self, candidate: Candidate) -> None:
        """Nothing: uniform samples do not depend on results."""
        pass


def warmup_sampler(D: int, box: tuple[float, float], streams: seeding.Streams, mechanisms: Mechanisms, codec: Codec) -> UniformSampler:
    """The run's warm-up: the paper's raw uniform ``box``, or the hardened encoded one (``encoded_warmup``)."""
    if mechanisms.encoded_warmup and codec.warp_params:
        from ..client.context import warmup_box

        return UniformSampler(D, warmup_box(box, codec.public_scale), streams, decode=codec.decode)
    return UniformSampler(D, box, streams)
