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
from .base import Bounds, Proposal, SearchProposer, clip_to_box

if TYPE_CHECKING:
    from ..client.codec import Codec
    from ..client.mechanisms import Mechanisms

Decode = Callable[[np.ndarray], np.ndarray]


class UniformSampler(SearchProposer):
    """Uniform samples in ``box``, shape (D,) each; sample m comes from its own seeded stream (the
    same whether or not the run was interrupted). The paper's warm-up (Algorithm 1, line 1).
    """

    def __init__(
        self, D: int, box: Bounds, streams: seeding.Streams, *, source: str = "warmup", decode: Decode | None = None,
        clip: Bounds | None = None,
    ) -> None:
        """``streams``: the run's random streams (sample m is draw m of ``seeding.WARMUP``).
        ``box``: (low, high), two numbers or two arrays of shape (D,) (an MLP's per-layer draws).
        ``decode`` given: ``box`` is a box of the encoded space and samples are decoded to raw ones,
        then clipped into ``clip`` when given (an MLP's layer boxes)."""
        self.D = D
        self.box = box
        self.streams = streams
        self.source = source
        self.decode = decode
        self.clip = clip

    def ask(self, iteration: int) -> Proposal:
        # One stream per sample, so sample m is the same whether or not the run was interrupted.
        """Sample ``iteration`` of the stream (decoded to raw theta when ``decode`` is given)."""
        lo, hi = self.box
        theta = self.streams.rng(seeding.WARMUP, iteration).uniform(lo, hi, size=self.D)
        if self.decode is not None:
            theta = np.asarray(self.decode(theta), dtype=np.float64)
            if self.clip is not None:
                theta, clipped = clip_to_box(theta, self.clip)
                return Proposal(theta=theta, source=self.source, clipped=clipped)
        return Proposal(theta=theta, source=self.source)

    def tell(self, candidate: Candidate) -> None:
        """Nothing: uniform samples do not depend on results."""
        pass


def warmup_sampler(D: int, box: tuple[float, float], streams: seeding.Streams, mechanisms: Mechanisms, codec: Codec,
                   *, init: Bounds | None = None, bounds: Bounds | None = None) -> UniformSampler:  # fmt: skip
    """The run's warm-up: the paper's raw uniform ``box``, or the hardened encoded one (``encoded_warmup``).

    An MLP passes ``init``, its scaled initialisation per layer (``PolicySpec.init_bounds``: uniform
    on +-1/sqrt(fan_in), two arrays of shape (D,)), drawn instead of ``box`` from the same keyed
    stream, and ``bounds``, its layer boxes, into which an encoded warm-up's decoded draws are clipped.
    """
    if mechanisms.encoded_warmup and codec.warp_params:
        from ..client.context import warmup_box

        return UniformSampler(D, warmup_box(box, codec.warmup_scale), streams, decode=codec.decode, clip=bounds)
    return UniformSampler(D, box if init is None else init, streams)
