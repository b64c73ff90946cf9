"""Every random stream of a run derives from the run seed, so a resumed run replays it exactly.

Streams are separated by a fixed tag so that, e.g., the episodes of candidate 3 never share
seeds with the final evaluation. Secrets are *not* derived from here: they come from the OS (or
a grid's master key), and so does everything a provider must not be able to replay: the
request's sampling seed is keyed by the secrets (``Codec.sampling_seed``).
"""

from __future__ import annotations

import numpy as np

WARMUP = 1
EPISODES = 2
FINAL_EVAL = 3
FALLBACK = 4
LLM_SAMPLING = 5


def _seq(seed: int, stream: int, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(entropy=int(seed), spawn_key=(stream, int(index)))


def rng(seed: int, stream: int, index: int = 0) -> np.random.Generator:
    """The generator of draw ``index`` of ``stream`` (WARMUP, EPISODES, ...) for run seed ``seed``; independent across all three."""
    return np.random.default_rng(_seq(seed, stream, index))


def episode_seeds(seed: int, candidate_index: int, episodes: int) -> list[int]:
    """Episode seeds of one candidate; fixed by (run seed, candidate index)."""
    words = _seq(seed, EPISODES, candidate_index).generate_state(episodes, dtype=np.uint32)
    return [int(w) for w in words]


def final_eval_seeds(seed: int, episodes: int) -> list[int]:
    """Fresh seeds for the final evaluation, never used during search; `policy eval --seed` uses them too."""
    words = _seq(seed, FINAL_EVAL, 0).generate_state(episodes, dtype=np.uint32)
    return [int(w) for w in words]


def llm_seed(seed: int, iteration: int, attempt: int) -> int:
    """The per-request sampling seed runs sent before issue 16, derived from the run seed alone.

    No longer sent: a provider could search run seeds for it (docs/threat-model.md). Requests now
    carry ``Codec.sampling_seed``, keyed by the secrets; this stays so the audit and the attacks
    recognise old transcripts."""
    return int(_seq(seed, LLM_SAMPLING, iteration * 1000 + attempt).generate_state(1, dtype=np.uint32)[0] >> 1)
