"""Bounded history: the K entries with the highest (encoded) return, best last."""

from __future__ import annotations

from collections.abc import Sequence

from .encoded import EncodedEntry


def top_k(entries: Sequence[EncodedEntry], k: int) -> list[EncodedEntry]:
    """Sort_up(TopK_r~(history, min(K, |history|))). k == 0 keeps every entry.

    Ties keep the older entry lower (so among equals the newest is shown last, nearest the answer).
    Ranking on c*r equals ranking on r because c > 0.
    """
    if k < 0:
        raise ValueError(f"top_k: k must be >= 0, got {k}")
    ordered = sorted(entries, key=lambda e: (e.ret, e.index))
    return ordered if k == 0 else ordered[-k:]
