"""Every random stream of a run derives from the run seed (and, for new runs, the run's key), so a
resumed run replays it exactly.

Streams are separated by a fixed tag so that, e.g., the episodes of candidate 3 never share
seeds with the final evaluation. ``Streams`` is one run's set of streams: keyed by a secret
derived from the run's key file (``Secrets.subkey("streams")``), so no draw that shapes what the
provider sees (the warm-up, the episodes' initial states, fallback noise) is a public function of
the run seed; without a key (runs recorded before streams were keyed) they derive from the run
seed alone, as they always did. The final evaluation's seeds stay a public function of the run
seed (``final_eval_seeds``), so ``ppprops policy eval --seed`` reproduces it; they never reach a
prompt. Secrets themselves come from the OS (or a grid's master key), never from here.
"""

from __future__ import annotations

import numpy as np

WARMUP = 1
EPISODES = 2
FINAL_EVAL = 3
FALLBACK = 4
LLM_SAMPLING = 5
OPTIMIZER = 6  # a black-box optimizer's own seed (CMA-ES)
SELECTION = 7  # re-evaluation episodes of the selection stage
PACING = 8  # the keyed jitter of paced requests (llm.pacing)
STOP = 9  # the keyed delay of a search that reached its target return under a hardening (ppprops.stopping)


def _seq(seed: int, stream: int, index: int, key: tuple[int, ...] = ()) -> np.random.SeedSequence:
    entropy: int | list[int] = [int(seed), *key] if key else int(seed)
    return np.random.SeedSequence(entropy=entropy, spawn_key=(stream, int(index)))


class Streams:
    """The random streams of one run: ``rng(stream, index)`` and ``episode_seeds(index, n)``.

    ``key`` (32 bytes, ``Secrets.subkey("streams")``) mixes the run's secret into every stream, so
    a provider who knows the run seed still cannot replay the warm-up or the episodes' initial
    states; None gives the unkeyed streams of runs recorded before (``rng``/``episode_seeds`` below).
    """

    def __init__(self, seed: int, key: bytes | None = None) -> None:
        self.seed = int(seed)
        self.keyed = key is not None
        self._key: tuple[int, ...] = tuple(int.from_bytes(key[i:i + 4], "big") for i in range(0, len(key), 4)) if key else ()

    def __repr__(self) -> str:  # never print the key
        return f"Streams(seed={self.seed}, keyed={self.keyed})"

    def rng(self, stream: int, index: int = 0) -> np.random.Generator:
        """The generator of draw ``index`` of ``stream`` (WARMUP, FALLBACK, ...)."""
        return np.random.default_rng(_seq(self.seed, stream, index, self._key))

    def episode_seeds(self, candidate_index: int, episodes: int) -> list[int]:
        """Episode seeds of one candidate (its initial states), fixed by (seed, key, candidate index)."""
        words = _seq(self.seed, EPISODES, candidate_index, self._key).generate_state(episodes, dtype=np.uint32)
        return [int(w) for w in words]

    def int_seed(self, stream: int, index: int = 0) -> int:
        """One non-negative 31-bit integer from a stream (a library's own seed, e.g. pycma's)."""
        return int(_seq(self.seed, stream, index, self._key).generate_state(1, dtype=np.uint32)[0] >> 1)


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
    """The per-request sampling seed older runs sent, derived from the run seed alone.

    No longer sent: a provider could search run seeds for it (docs/threat-model.md). Requests now
    carry ``Codec.sampling_seed``, keyed by the secrets; this stays so the audit and the attacks
    recognise old transcripts."""
    return int(_seq(seed, LLM_SAMPLING, iteration * 1000 + attempt).generate_state(1, dtype=np.uint32)[0] >> 1)


def draw_seed() -> int:
    """A fresh run seed from the OS entropy source, below 2^31 (short enough to type back with ``--seed``)."""
    import secrets

    return secrets.randbelow(2**31)
