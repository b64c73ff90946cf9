"""Turns an LLM answer into exactly D finite numbers, or says precisely why it cannot.

Where the proposal comes from (one rule, for every server and model):

1. An answer the endpoint cut off at its token limit (``finish_reason`` ``length``) is never
   used, whatever it holds.
2. The content is split into reasoning and final text. Reasoning is every known reasoning
   syntax: ``<think>``/``<thinking>``/``<reasoning>``/``<thought>`` blocks, closed or not, the
   text before a lone closing tag (R1-style templates open the tag in the prompt), and gpt-oss
   harmony channels (``<|channel|>analysis<|message|>...``; only the ``final`` channel is final
   text). Code fences are dropped.
3. If the final text is not empty it is the only source: the requested answer object
   ``{"params": [...]}`` wins over any other form in it (a restated ``params[i]: v`` list or a
   quoted history list); without one, a bare JSON list, ``parameters``/``theta`` keys,
   ``params[i]: value`` lines or a bracketed list are read, and failing those a list written
   without brackets: one value per line (bullets, numbered lines, bare numbers, labelled values
   such as ``theta_3: 1.5`` or ``W[0][1] = 1.5``, table rows whose last cell is the value) or a
   line of numbers separated by commas or spaces. A list of the wrong size, in any of these
   layouts, is ``wrong_length``, never ``no_numbers``.
4. Only when the final text is empty is reasoning (the content's own and the server's separate
   ``reasoning_content``/``reasoning`` field) read, and then only for an explicit final answer:
   the last ``{"params": [...]}`` object in it, or else the last list of D numbers that follows
   an answer cue ("answer", "propose", "final", ...) on its line. Quoted lists are not answers.

A continuation of the document form (``wire.document``) is read by ``read_continuation``: the
document ends inside an open list, so the answer is ``[`` plus the continuation up to its first
``]`` (or up to where it stopped, when the request's stop sequence ``]`` ended it); whatever
follows is the model writing more document and is never read. The values' index
labels (``0:1.5,1:-2``) are dropped and must count 0, 1, 2, ... Rule 1 holds for it too, and the
numbers go through the same reader as a final text.

Typographic minus signs (U+2212, en and figure dashes) before a number read as ``-``; exponents
are accepted. The parser never raises on model output: failures come back as a typed result.
Whether a proposal merely repeats a history entry is the proposer's check (it knows what it showed).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf(?:inity)?)"
_TAGS = "think|thinking|reasoning|thought"
_BLOCK = re.compile(rf"<({_TAGS})>.*?(?:</\1>|$)", re.DOTALL | re.IGNORECASE)
_CLOSE = re.compile(rf"</({_TAGS})>", re.IGNORECASE)
_STRAY_TAG = re.compile(rf"</?(?:{_TAGS})>", re.IGNORECASE)
# gpt-oss harmony: <|start|>assistant<|channel|>NAME [to=...] [<|constrain|>json]<|message|>TEXT<|end|>
_HARMONY_HEAD = re.compile(
    r"(?:<\|start\|>[^<]*)?<\|channel\|>\s*(?P<channel>[A-Za-z_]+)[^<]*(?:<\|constrain\|>[^<]*)?<\|message\|>"
)
_HARMONY_STOP = re.compile(r"<\|(?:end|return|call|start|channel)\|>")
_SPECIAL = re.compile(r"<\|[a-z_]+\|>")
# the same markup with its special tokens decoded to nothing ("analysis...assistantfinal{...}")
_HARMONY_FLAT = re.compile(r"^\s*analysis.*assistantfinal", re.DOTALL)
_FENCE = re.compile(r"```[a-zA-Z0-9_-]*\n?|```")
_MINUS = re.compile(r"[\u2212\u2012\u2013\ufe63\uff0d](?=\s*[\d.])")
_INDEXED = re.compile(r"params?\s*\[\s*(\d+)\s*\]\s*[:=]\s*(" + _NUM + ")", re.IGNORECASE)
_BRACKETS = re.compile(r"\[([^\[\]]*)\]")
_REFUSAL = re.compile(r"\b(i can(?:no|')t|i cannot|i'm sorry|i am sorry|unable to|as an ai)\b", re.IGNORECASE)
_CUE = re.compile(r"\b(answer|propos\w*|final|output|submit|respond|go with|choose|my pick)\b", re.IGNORECASE)
_OPEN_TAIL = re.compile(r"\[([^\[\]]*)$")

# "context_full" is not the parser's: the client tells it apart from "length" by the token counts
# (``llm.client.context_full``), and the proposer records it in its place.
ERROR_KINDS = (
    "empty", "reasoning_only", "length", "context_full", "refusal", "no_numbers", "truncated", "wrong_length",
    "non_finite", "several_vectors", "labels",
)


@dataclass(frozen=True)
class ParseResult:
    """What an answer gave: the D numbers (``values``), or None with an ``error`` kind and a ``detail`` in words."""

    values: tuple[float, ...] | None
    error: str | None = None  # one of ERROR_KINDS when values is None
    detail: str = ""  # why, in words that may be shown to the model (no markup, no HTTP text)
    source: str = "content"  # where the values came from: content | reasoning

    @property
    def ok(self) -> bool:
        """True when the answer gave a usable vector."""
        return self.values is not None


@dataclass(frozen=True)
class Split:
    """An answer's content cut into its final text and the reasoning found inside it."""

    final: str
    reasoning: str


def _fail(kind: str, detail: str) -> ParseResult:
    return ParseResult(values=None, error=kind, detail=detail)


def _harmony(text: str) -> Split:
    """Final text = the ``final`` channel plus anything outside a channel; other channels are reasoning."""
    final: list[str] = []
    reasoning: list[str] = []
    pos = 0
    for head in _HARMONY_HEAD.finditer(text):
        if head.start() < pos:
            continue
        final.append(text[pos:head.start()])
        stop = _HARMONY_STOP.search(text, head.end())
        end = stop.start() if stop else len(text)
        (final if head.group("channel").lower() == "final" else reasoning).append(text[head.end():end])
        pos = end
    final.append(text[pos:])
    return Split(_SPECIAL.sub(" ", "".join(final)), "\n".join(reasoning))


def split_reasoning(content: str | None) -> Split:
    """Cut ``content`` into final text and reasoning (rule 2 of the module docstring)."""
    text = content or ""
    reasoning: list[str] = []
    if "<|" in text:
        h = _harmony(text)
        text, reasoning = h.final, [h.reasoning]
    elif _HARMONY_FLAT.match(text):
        cut = text.rindex("assistantfinal")
        reasoning, text = [text[:cut]], text[cut + len("assistantfinal"):]
    close = _CLOSE.search(text)
    if close and not re.search(rf"<{re.escape(close.group(1))}>", text[: close.start()], re.IGNORECASE):
        reasoning.append(text[: close.start()])  # a lone closing tag: the template opened it in the prompt
        text = text[close.end():]
    reasoning += [m.group(0) for m in _BLOCK.finditer(text)]
    text = _STRAY_TAG.sub(" ", _BLOCK.sub(" ", text))
    return Split(_FENCE.sub(" ", text).strip(), "\n".join(r for r in reasoning if r.strip()))


def final_text(content: str | None) -> str:
    """The final text of an answer, without reasoning or markup: what may be echoed back to the model."""
    return split_reasoning(content).final


def _normalise(text: str) -> str:
    return _MINUS.sub("-", text)


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


_INDEX = re.compile(r"\[\s*\d{1,4}\s*\]")


def _index_at(text: str, i: int) -> bool:
    """True when the ``[`` at ``i`` opens an index (``W[0]``, ``b[2]``, ``x_[1]``): one integer in
    brackets right after a name or another index."""
    return i > 0 and (text[i - 1].isalnum() or text[i - 1] in "_]") and _INDEX.match(text, i) is not None


def _json_values(text: str) -> list[tuple[int, object]]:
    """(offset, value) of every JSON object or list that decodes at some position of the text."""
    found: list[tuple[int, object]] = []
    dec = json.JSONDecoder()
    i = 0
    while i < len(text):
        if text[i] == "[" and _index_at(text, i):
            i += 1  # an index, as in W[0][1] or b[2], not a list
        elif text[i] in "[{":
            try:
                obj, end = dec.raw_decode(text, i)
            except ValueError:
                i += 1
                continue
            found.append((i, obj))
            i = end
        else:
            i += 1
    return found


def _params_objects(values: list[tuple[int, object]]) -> list[tuple[int, list[float]]]:
    """The requested answer objects: {"params": [numbers]}."""
    out = []
    for at, obj in values:
        if isinstance(obj, dict) and isinstance(obj.get("params"), list):
            vec = _to_floats(obj["params"])
            if vec:
                out.append((at, vec))
    return out


def _other_json_vectors(values: list[tuple[int, object]]) -> list[list[float]]:
    found: list[list[float]] = []
    for _, obj in values:
        vec = None
        if isinstance(obj, dict):
            for key in ("parameters", "theta"):
                if isinstance(obj.get(key), list):
                    vec = _to_floats(obj[key])
                    break
        elif isinstance(obj, list):
            vec = _to_floats(obj)
        if vec:
            found.append(vec)
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


def _bracket_vectors(text: str) -> list[tuple[int, list[float]]]:
    out: list[tuple[int, list[float]]] = []
    for m in _BRACKETS.finditer(text):
        if _index_at(text, m.start()):
            continue  # an index, as in W[0][1] or b[2], not a list
        body = m.group(1)
        nums = re.findall(_NUM, body, flags=re.IGNORECASE)
        rest = re.sub(_NUM, "", body, flags=re.IGNORECASE)
        if nums and re.fullmatch(r"[\s,;]*", rest):
            out.append((m.start(), [float(v) for v in nums]))
    return out


# One value per line: "- 1.5", "* 1.5", "3. 1.5", "(3) 1.5", "1.5,", "p3 = 1.5", "theta_3: 1.5",
# "W[0][1] = 1.5"; after a bullet or an item number, any short label: "- pole angle weight: 1.5".
_LABEL = r"\**(?:params?|parameters?|theta|\u03b8|weights?|w|p|x|b)?[ _]?(?:\[?\d{1,4}\]?){1,2}\**"
_ITEM_LINE = re.compile(
    r"^\s*(?:(?:[-*+\u2022\u2023\u25e6]\s+|\(?\d{1,4}[.)]\s+|\(\d{1,4}\)\s*)(?:[^:=\n]{1,60}[:=]\s*)?"
    r"|(?:" + _LABEL + r"\s*[:=]\s*)?)"
    r"\**(" + _NUM + r")\**\s*[,;]?\s*$",
    re.IGNORECASE,
)
_TABLE_ROW = re.compile(r"^\s*\|(.*)\|\s*$")
_TABLE_RULE = re.compile(r"^[\s|:+-]*$")
# A line of two or more numbers and separators only, after a short label without digits:
# "1.5, -2, 0.3", "1.5 -2 0.3", "My proposal: 1.5, -2, 0.3".
_NUMBER_LINE = re.compile(r"^\s*(?:[^:=\d\n]{0,60}[:=]\s*)?(?:" + _NUM + r")(?:\s*[,;]?\s*(?:" + _NUM + r"))+\s*[,;.]?\s*$", re.IGNORECASE)


def _line_value(line: str) -> float | None:
    """The one value of a list line (bullet, numbered item, bare number, labelled value, table
    row whose last cell is a number), or None when the line is not one."""
    row = _TABLE_ROW.match(line)
    if row:
        cells = [c.strip().strip("*") for c in row.group(1).split("|")]
        if cells and re.fullmatch(_NUM, cells[-1], flags=re.IGNORECASE):
            return float(cells[-1])
        return None
    m = _ITEM_LINE.match(line)
    return float(m.group(1)) if m else None


def _line_lists(text: str) -> list[list[float]]:
    """Vectors written without brackets: runs of two or more lines that hold one value each
    (bullets, numbered lines, one number per line, table rows; blank lines, a table's header and
    rule lines may sit between them), and lines of two or more numbers separated by commas or
    spaces. Each run, and each such line, is one vector."""
    found: list[list[float]] = []
    run: list[float] = []

    def close() -> None:
        if len(run) >= 2:
            found.append(list(run))
        run.clear()

    for line in text.splitlines():
        if not line.strip() or (run and _TABLE_RULE.fullmatch(line)):
            continue
        value = _line_value(line)
        if value is not None:
            run.append(value)
            continue
        close()
        if _NUMBER_LINE.match(line):
            found.append([float(v) for v in re.findall(_NUM, line.split(":")[-1].split("=")[-1], flags=re.IGNORECASE)])
    close()
    return found


def _distinct(vectors: list[list[float]]) -> list[list[float]]:
    seen: list[list[float]] = []
    for v in vectors:
        if not any(len(v) == len(s) and all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(v, s)) for s in seen):
            seen.append(v)
    return seen


def _one(vectors: list[list[float]], D: int) -> ParseResult:
    right = _distinct([v for v in vectors if len(v) == D])
    if not right:
        lengths = sorted({len(v) for v in vectors})
        return _fail("wrong_length", f"expected {D} numbers, got {', '.join(map(str, lengths))}")
    if len(right) > 1:
        return _fail("several_vectors", f"the answer held {len(right)} different vectors of {D} numbers")
    return _finite(right[0])


def _finite(vec: list[float], source: str = "content") -> ParseResult:
    if not all(math.isfinite(v) for v in vec):
        return _fail("non_finite", "the vector held NaN or infinite values")
    return ParseResult(values=tuple(vec), source=source)


def _parse_final(body: str, D: int) -> ParseResult:
    body = _normalise(body)
    values = _json_values(body)
    requested = _params_objects(values)
    if requested:  # the object the prompt asks for wins over restated or quoted vectors
        return _one([v for _, v in requested], D)
    # The indexed form goes before bare lists: its "[0]" pieces would otherwise read as one-element lists.
    indexed = _indexed_vector(body)
    vectors = [indexed] if indexed else (_other_json_vectors(values) or [v for _, v in _bracket_vectors(body)])
    if not vectors:
        tail = _OPEN_TAIL.search(body)
        if tail and re.search(_NUM, tail.group(1), flags=re.IGNORECASE):
            n = len(re.findall(_NUM, tail.group(1), flags=re.IGNORECASE))
            return _fail("truncated", f"the answer stopped after {n} of {D} numbers, before the closing bracket")
        vectors = _line_lists(body)
    if not vectors:
        if _REFUSAL.search(body):
            return _fail("refusal", "the answer declined to propose parameters")
        return _fail("no_numbers", "no parameter vector was found in the answer")
    return _one(vectors, D)


def _explicit_answer(reasoning: str, D: int) -> ParseResult | None:
    """Rule 4: the last {"params": [...]} of D numbers, else the last D-list after an answer cue."""
    text = _normalise(reasoning)
    objects = [v for _, v in _params_objects(_json_values(text)) if len(v) == D]
    if objects:
        return _finite(objects[-1], "reasoning")
    cued = []
    for at, vec in _bracket_vectors(text):
        line_start = text.rfind("\n", 0, at) + 1
        if len(vec) == D and _CUE.search(text[line_start:at]):
            cued.append(vec)
    return _finite(cued[-1], "reasoning") if cued else None


def read_answer(content: str | None, reasoning: str | None, D: int, *, finish_reason: str | None = None) -> ParseResult:
    """The proposal in one chat answer, by the rule of the module docstring.

    ``content`` is the message content, ``reasoning`` the server's separate reasoning field (or
    None), ``finish_reason`` the choice's. Returns a ``ParseResult`` whose ``source`` says where
    the values came from; never raises.
    """
    if finish_reason == "length":
        return _fail("length", "the answer was cut off at the token limit before it was complete; answer at once")
    if finish_reason == "content_filter":
        return _fail("refusal", "the answer was withheld by a content filter")
    split = split_reasoning(content)
    if split.final:
        return _parse_final(split.final, D)
    thoughts = "\n".join(t for t in (split.reasoning, reasoning or "") if t and t.strip())
    if not thoughts:
        return _fail("empty", "the answer was empty")
    found = _explicit_answer(thoughts, D)
    if found is None:
        return _fail("reasoning_only", "the answer held only reasoning and no final answer")
    return found


def parse_answer(text: str | None, D: int) -> ParseResult:
    """Extract exactly D finite numbers from an answer's content (no separate reasoning field)."""
    return read_answer(text, None, D)


def read_continuation(text: str | None, D: int, *, opening: str = "[", finish_reason: str | None = None) -> ParseResult:
    """The proposal in the continuation of a document that ends with ``opening`` (an open list).

    The answer is ``opening`` + the text up to and including its first ``]``; text after that
    is ignored. A continuation that ended by itself (``finish_reason`` ``stop``) without a ``]``
    stopped at the request's stop sequence ``]``, which servers do not return: it is read as
    closed there. An answer cut off at the token limit is never used (``length``); an empty
    continuation is ``empty``; one that never closes the list is ``truncated``. Never raises.
    """
    if finish_reason == "length":
        return _fail("length", "the answer was cut off at the token limit before it was complete")
    if finish_reason == "content_filter":
        return _fail("refusal", "the answer was withheld by a content filter")
    body = text or ""
    if not body.strip():
        return _fail("empty", "the answer was empty")
    close = body.find("]")
    if close < 0 and finish_reason == "stop":
        body, close = body + "]", len(body)  # stopped at the stop sequence "]"
    head = body if close < 0 else body[: close + 1]
    head, bad = _unlabel(head)
    if bad:
        return _fail("labels", bad)
    return _parse_final(opening + head, D)


_LABELLED = re.compile(r"^\s*(\d+)\s*:\s*(.*)$", re.DOTALL)


def _unlabel(text: str) -> tuple[str, str]:
    """Drop the index labels of a labelled list (``0:1.5,1:-2]`` -> ``1.5,-2]``). Items with no
    label are left as they are; labels must count 0, 1, 2, ... (else the second value is why)."""
    items = text.split(",")
    out = []
    for i, item in enumerate(items):
        m = _LABELLED.match(item)
        if m is None:
            out.append(item)
            continue
        if int(m.group(1)) != i:
            return text, f"the value at position {i} was labelled {m.group(1)}; label the values 0, 1, 2, ... in order"
        out.append(m.group(2))
    return ",".join(out), ""
