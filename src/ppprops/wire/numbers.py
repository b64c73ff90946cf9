"""How numbers are written in prompts. One place, so the audit knows every notation used."""

from __future__ import annotations

import math


def fmt(x: float, decimals: int) -> str:
    """Fixed-point with a set number of decimals; no exponent, no negative zero."""
    s = f"{x:.{decimals}f}"
    if s.startswith("-") and float(s) == 0.0:
        s = s[1:]
    return s


def fmt_sig(x: float, digits: int, decimals: int) -> str:
    """``digits`` significant digits but never more than ``decimals`` decimals (fixed-point,
    no exponent): -33.77 -> -33.8, 0.59 -> 0.59, 0.004 -> 0 with (3, 2). ``digits`` 0 is plain ``fmt``."""
    if digits <= 0 or x == 0 or not math.isfinite(x):
        return fmt(x, decimals)
    return fmt(x, max(0, min(decimals, digits - 1 - math.floor(math.log10(abs(x))))))


def fmt_vector(values: tuple[float, ...] | list[float], decimals: int, *, digits: int = 0, sep: str = ", ") -> str:
    """``[v0, v1, ...]`` with each value in ``digits`` significant digits (0: ``decimals`` fixed decimals)."""
    return "[" + sep.join(fmt_sig(v, digits, decimals) for v in values) + "]"


def fmt_value(v: float | str, decimals: int) -> str:
    """A diagnostic as printed: text as is, integers without decimals, other numbers with ``decimals`` decimals."""
    if isinstance(v, str):
        return v
    if float(v).is_integer():
        return str(int(v))
    return fmt(v, decimals)
