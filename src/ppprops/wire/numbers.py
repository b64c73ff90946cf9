"""How numbers are written in prompts. One place, so the audit knows every notation used."""

from __future__ import annotations


def fmt(x: float, decimals: int) -> str:
    """Fixed-point with a set number of decimals; no exponent, no negative zero."""
    s = f"{x:.{decimals}f}"
    if s.startswith("-") and float(s) == 0.0:
        s = s[1:]
    return s


def fmt_vector(values: tuple[float, ...] | list[float], decimals: int) -> str:
    return "[" + ", ".join(fmt(v, decimals) for v in values) + "]"


def fmt_value(v: float | str, decimals: int) -> str:
    if isinstance(v, str):
        return v
    if float(v).is_integer():
        return str(int(v))
    return fmt(v, decimals)
