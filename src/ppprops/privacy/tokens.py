"""Printed numbers: the value a token stands for and the precision it was printed with."""

from __future__ import annotations

import functools
import re

_TOKEN = re.compile(r"([-+]?)(\d*)(?:\.(\d*))?(?:[eE]([-+]?\d+))?")


@functools.lru_cache(maxsize=1 << 16)  # the audit reads the same printed entries in many requests
def token_value(tok: str) -> tuple[float, float] | None:
    """A printed number and half its last printed digit (how far the value it renders may lie)."""
    m = _TOKEN.fullmatch(tok.strip())
    if m is None or not (m.group(2) or m.group(3)):
        return None
    decimals = len(m.group(3) or "")
    exponent = int(m.group(4) or 0)
    return float(tok), 0.5 * 10.0 ** (exponent - decimals)


def renders(value: float, printed: float, tol: float) -> bool:
    """Could ``value`` be printed as ``printed`` at that precision (rounding, either tie rule)?"""
    return abs(value - printed) <= tol * (1 + 1e-9) + 1e-12 * max(1.0, abs(value))
