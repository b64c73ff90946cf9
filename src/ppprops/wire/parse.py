"""Turns an LLM answer into exactly D finite numbers, or says precisely why it cannot.

Accepted forms: a JSON object with a "params" list, a bare JSON list, or ``params[i]: value``
lines; reasoning blocks (<think>...</think>) and code fences are stripped first, exponents are
accepted. The parser never raises on model output: failures come back as a typed result.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf(?:inity)?)"
_REASONING = re.compile(r"<(think|thinking|reasoning)>.*?(</\1>|$)", re.DOTALL | re.IGNORECASE)
_FENCE = re.compile(r"```[a-zA-Z0-9_-]*\n?|```")
_INDEXED = re.compile(r"params?\s*\[\s*(\d+)\s*\]\s*[:=]\s*(" + _NUM + ")", re.IGNORECASE)
_BRACKETS = re.compile(r"\[([^\[\]]*)\]")
_REFUSAL = re.compile(r"\b(i can(?:no|')t|i cannot|i'm sorry|i am sorry|unable to|as an ai)\b", re.IGNORECASE)

ERROR_KINDS = ("empty", "refusal", "no_numbers", "truncated", "wrong_length", "non_finite", "several_vectors")
_OPEN_TAIL = re.compile(r"\[([^\[\]]*)$")


@dataclass(frozen=True)
class ParseResult:
    values: tuple[float, ...] | None
    error: str | None = None  # one of ERROR_KINDS when values is None
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.values is not None


def _fail(kind: str, detail: str) -> ParseResult:
    return ParseResult(values=None, error=kind, detail=detail)


def _to_floats(items: list[object]) -> list[float] | None:
    out: list[float] = []
    for it in items:
        if isinstance(it, bool) or not isinstance(it, (int, float, str)):
            return None
        try:
            out.append(float(it))
        except ValueError:
            return None
    return out


def _json_vectors(text: str) -> list[list[float]]:
    """Every JSON value in the text that is a number list or an object with a 'params' number list."""
    found: list[list[float]] = []
    dec = json.JSONDecoder()
    i = 0
    while i < len(text):
        if text[i] in "[{":
            try:
                obj, end = dec.raw_decode(text, i)
            except ValueError:
                i += 1
                continue
            vec = None
            if isinstance(obj, dict):
                for key in ("params", "parameters", "theta"):
                    if isinstance(obj.get(key), list):
                        vec = _to_floats(obj[key])
                        break
            elif isinstance(obj, list):
                vec = _to_floats(obj)
            if vec:
                found.append(vec)
            i = end
        else:
            i += 1
    return found


def _indexed_vector(text: str) -> list[float] | None:
    pairs = _INDEXED.findall(text)
    if not pairs:
        return None
    by_index: dict[int, float] = {}
    for idx, val in pairs:
        by_index[int(idx)] = float(val)  # a later line for the same index wins (models restate)
    # with gaps the vector comes out shorter than its highest index, which reads as wrong_length
    return [by_index[k] for k in sorted(by_index)]


def _bracket_vectors(text: str) -> list[list[float]]:
    out: list[list[float]] = []
    for body in _BRACKETS.findall(text):
        nums = re.findall(_NUM, body, flags=re.IGNORECASE)
        rest = re.sub(_NUM, "", body, flags=re.IGNORECASE)
        if nums and re.fullmatch(r"[\s,;]*", rest):
            out.append([float(v) for v in nums])
    return out


def _distinct(vectors: list[list[float]]) -> list[list[float]]:
    seen: list[list[float]] = []
    for v in vectors:
        if not any(len(v) == len(s) and all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(v, s)) for s in seen):
            seen.append(v)
    return seen


def clean(text: str) -> str:
    text = _REASONING.sub(" ", text)
    return _FENCE.sub(" ", text).strip()


def parse_answer(text: str | None, D: int) -> ParseResult:
    """Extract exactly D finite numbers from an answer."""
    if text is None or not text.strip():
        return _fail("empty", "the answer was empty")
    body = clean(text)
    if not body:
        return _fail("empty", "the answer held only reasoning, no final content")
    # The indexed form goes first: its "[0]" pieces would otherwise read as one-element JSON lists.
    indexed = _indexed_vector(body)
    vectors = [indexed] if indexed else (_json_vectors(body) or _bracket_vectors(body))
    if not vectors:
        tail = _OPEN_TAIL.search(body)
        if tail and re.search(_NUM, tail.group(1), flags=re.IGNORECASE):
            n = len(re.findall(_NUM, tail.group(1), flags=re.IGNORECASE))
            return _fail("truncated", f"the answer stopped after {n} of {D} numbers, before the closing bracket")
        if _REFUSAL.search(body):
            return _fail("refusal", "the answer declined to propose parameters")
        return _fail("no_numbers", "no parameter vector was found in the answer")
    right = _distinct([v for v in vectors if len(v) == D])
    if not right:
        lengths = sorted({len(v) for v in vectors})
        return _fail("wrong_length", f"expected {D} numbers, got {', '.join(map(str, lengths))}")
    if len(right) > 1:
        return _fail("several_vectors", f"the answer held {len(right)} different vectors of {D} numbers")
    vec = right[0]
    if not all(math.isfinite(v) for v in vec):
        return _fail("non_finite", "the vector held NaN or infinite values")
    return ParseResult(values=tuple(vec))
