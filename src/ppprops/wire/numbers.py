"""How numbers are written in prompts. One place, so the audit knows every notation used."""

from __future__ import annotations

import math
from dataclasses import dataclass


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


@dataclass(frozen=True)
class NumberFormat:
    """How a prompt form writes the encoded parameters, and so how their answers are written.

    ``decimal``: ``digits`` significant digits with at most ``decimals`` decimals (``fmt_sig``),
    as every run stored before the grid existed was written. ``grid``: integers, no decimal point;
    the client puts the encoded values on an integer grid with a secret global factor
    (``client.codec.Codec``: about ``[-GRID_SPAN, GRID_SPAN]`` across the box), so a value is one to
    three digits and rounding it moves it by at most half a grid step; the chat form's fixed prose is
    terser (``terse``: the
    paper's five sections, with the same content, in fewer words). Returns, reward components and
    diagnostics are written in ``decimals`` decimals in every format. A run stores its format, so
    the audit rebuilds each request in the words and numbers it was sent in.

    The print (``wire.prompt.params_text``), the answer grammars (``wire.forms.params_grammar``,
    ``wire.document.continuation_grammar``), the repeat check (``wire.turns.repeats_history``,
    which compares printed vectors) and the audit (which rebuilds every entry with the form) all
    take the digits and decimals of a parameter from here.
    """

    name: str
    integers: bool
    words: str  # what the interaction section calls the numbers of an answer
    # the document form labels one value per row of W (and the first bias), not every value (wire.document.labelled:
    # ``[0:v,v,...,8:v,...]``); no built-in format sets it yet (benchmark 11 measures whether the model keeps its place)
    row_labels: bool = False
    # the chat form's fixed prose in fewer words (the ``*_terse`` templates, ``wire.prompt.wording``); the decimal
    # format keeps the words every run stored before the grid was sent, so the audit rebuilds those exactly
    terse: bool = False

    def digits(self, digits: int) -> int:
        """Significant digits of a parameter: ``digits`` (``--param-digits``), or 0 (fixed decimals) on the grid."""
        return 0 if self.integers else digits

    def decimals(self, decimals: int) -> int:
        """Decimals of a parameter: ``decimals`` (``--decimals``), or 0 on the grid."""
        return 0 if self.integers else decimals

    def number_rule(self) -> str:
        """The GBNF right-hand side of one answer number: an optional sign, then up to four integer
        digits on the grid, or up to three integer digits and up to three decimals in the decimal format."""
        if self.integers:
            return '"-"? [0-9] [0-9]? [0-9]? [0-9]?'
        return '"-"? [0-9] [0-9]? [0-9]? ("." [0-9] [0-9]? [0-9]?)?'


DECIMAL = NumberFormat("decimal", integers=False, words="numbers")
# row_labels stays off: with one label per row the embedded model kept its place less well on Ant-Ultra (benchmark 11)
GRID = NumberFormat("grid", integers=True, words="integers", terse=True)
# By name, as a run's config stores it (``--number-format``); runs stored before formats existed are ``decimal``.
NUMBER_FORMATS: dict[str, NumberFormat] = {f.name: f for f in (GRID, DECIMAL)}
GRID_SPAN = 999  # the grid's nominal half-width: the largest encoded value the box maps to (client.codec)


def number_format(name: str) -> NumberFormat:
    """The format called ``name``; ValueError naming the known ones for any other."""
    if name not in NUMBER_FORMATS:
        raise ValueError(f"unknown number format {name!r} (known: {', '.join(NUMBER_FORMATS)})")
    return NUMBER_FORMATS[name]
