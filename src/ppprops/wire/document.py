"""The document form of the prompt: a history written as a document for a base model to continue.

The embedded Gemma 3 270M is a base model (its GGUF carries no chat template): asked through a
chat wrapper it was never trained on, it copies entries or writes patterns. What it does well is
continue a document. So for it the prompt is a short header, the shown history as ``return:`` /
``params:`` blocks from the lowest return to the highest, and one open block whose return is a
target above the best shown one; the model writes the parameters that complete it::

    # CartPole: linear policy search. ...

    return: 12.40
    params: [1.21,-0.3,...]

    ...

    return: 97.20
    params: [

The target is computed from the shown (already encoded) returns only, so it discloses nothing the
history does not. The continuation is sent to a completions endpoint with a grammar that allows
exactly D numbers and the closing bracket (``continuation_grammar``); ``wire.parse.read_continuation``
reads it. Capable chat models keep the paper's instruction prompt (``wire.prompt.build_prompt``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

from .encoded import EncodedEntry, PromptContext
from .numbers import DECIMAL, fmt
from .prompt import params_text, render

# The open block asks for best + TARGET_LIFT * min(best - worst, |best|) of the shown returns.
TARGET_LIFT = 0.2
# With one shown return, or all equal, the spread is taken as this share of |best|.
TARGET_FLOOR = 0.1
# Sampling temperatures of the document form when --temperature is not set: LLM iteration i uses
# TEMPERATURES[i % len]. Low temperatures make the base model copy and refine the best entries,
# 1.0 makes it explore; no single one served every task (benchmarks/RESULTS.md). A retry of the
# same iteration (after a repeated entry or an unusable answer) adds RETRY_STEP per attempt.
TEMPERATURES = (0.6, 1.0)
RETRY_STEP = 0.3
MAX_TEMPERATURE = 2.0
# Exploration when the search is stuck: after STALL_AFTER LLM iterations in a row that did not raise
# the best shown return, an iteration is sampled at EXPLORE_TEMPERATURE from the untruncated
# distribution (EXPLORE_SAMPLING turns llama.cpp's default top-p 0.95, min-p 0.05 and top-k 40 off).
# Measured on a stuck CartPole document: the model copies the best entry so surely that with the
# truncation on, temperatures 1.0, 1.5 and 2.0 give the same continuation (RMS step 0.05 in the
# encoded space); untruncated at 2.0 the median step is 0.87, with jumps past 3 (benchmarks/RESULTS.md).
STALL_AFTER = 3
EXPLORE_TEMPERATURE = 2.0
EXPLORE_SAMPLING: dict[str, float] = {"top_p": 1.0, "min_p": 0.0, "top_k": 0}
OPENING = "["  # the document ends inside the open list; the continuation starts after it
LABEL = ":"  # between a value's index and the value


def document_target(history: Sequence[EncodedEntry], lift: float = TARGET_LIFT) -> float:
    """The return written in the open block: ``best + lift * min(spread, |best|)``, where spread is
    ``best - worst`` of the shown (encoded) returns (``0.1 |best|`` when they are all equal). The
    cap keeps the target on the side of zero the best is on (asking a base model for a positive
    return after only negative ones made it write junk). Same scale as the history, computed
    from nothing else. Raises ``ValueError`` on a history without a finite return."""
    rets = [e.ret for e in history if math.isfinite(e.ret)]
    if not rets:
        raise ValueError("the document form needs at least one history entry with a finite return")
    best, worst = max(rets), min(rets)
    spread = best - worst if best > worst else TARGET_FLOOR * abs(best)
    return best + lift * min(spread, abs(best))


def document_temperature(iteration: int, attempt: int, temperature: float | None = None, stalled: int = 0) -> float:
    """The sampling temperature of one document request: ``temperature`` (``--temperature``), or
    ``TEMPERATURES[iteration % len]``, or ``EXPLORE_TEMPERATURE`` when ``stalled`` (LLM iterations
    in a row that did not raise the best shown return) has reached ``STALL_AFTER``; plus
    ``RETRY_STEP`` per retry, at most 2. Public inputs only: the audit recomputes it."""
    if temperature is not None:
        base = temperature
    elif stalled >= STALL_AFTER:
        base = EXPLORE_TEMPERATURE
    else:
        base = TEMPERATURES[iteration % len(TEMPERATURES)]
    return min(MAX_TEMPERATURE, base + RETRY_STEP * attempt)


def document_sampling(stalled: int, temperature: float | None = None) -> dict[str, float]:
    """The sampling fields of an exploratory request (``EXPLORE_SAMPLING``: no truncation) when the
    schedule explores (``stalled`` >= ``STALL_AFTER`` and no ``--temperature``), else none."""
    return dict(EXPLORE_SAMPLING) if temperature is None and stalled >= STALL_AFTER else {}


def labelled(ctx: PromptContext, params: Sequence[float]) -> str:
    """Parameters as one list whose values carry their index, ``[0:1.21,1:-0.3,...]``, each value
    in the list form of ``wire.prompt.params_text``; in a format with row labels
    (``NumberFormat.row_labels``; no built-in format sets it yet) only the first value of each row
    is labelled, ``[0:12,-3,5,3:40,...]`` (``is_labelled``). The labels let the small model copy a
    value from the same coordinate of an entry above (without them it lost its place in lists of 21
    numbers and wrote junk; benchmarks/RESULTS.md; benchmark 11 measures one label per row)."""
    values = params_text(_as_list(ctx), tuple(params)).strip("[]").split(",")
    return "[" + ",".join(f"{i}{LABEL}{v}" if is_labelled(ctx, i) else v for i, v in enumerate(values)) + "]"


def is_labelled(ctx: PromptContext | None, j: int) -> bool:
    """Whether value ``j`` carries its index: every value, or in a format with ``row_labels`` the
    first of each row of ``n_a`` values (a row of W, then the biases)."""
    if ctx is None or not ctx.numbers.row_labels:
        return True
    return j % max(1, ctx.n_a) == 0


def document_entry(ctx: PromptContext, e: EncodedEntry) -> str:
    """One shown policy: ``return: R``, then ``params: [0:..,1:..]`` (``labelled``). Reward
    components and diagnostics are not written: they cost tokens the small model does not use,
    so the document form shows less than the chat form under every preset, never more."""
    if not isinstance(e, EncodedEntry):  # a raw Candidate must never be formatted into a prompt
        raise TypeError(f"prompt history takes EncodedEntry values only, got {type(e).__name__}")
    return render("document_entry", ret=fmt(e.ret, ctx.decimals), params=labelled(ctx, e.params))


def build_document(ctx: PromptContext, history: Sequence[EncodedEntry]) -> str:
    """The whole document, ending just after ``params: [`` of the open block.

    ``history`` is the shown history, lowest return first (``wire.top_k``). The parameters are
    always written as one list (the open block continues one), whatever ``ctx.params_style``.
    """
    body = "\n\n".join(document_entry(ctx, e) for e in history)
    return render("document", title=ctx.title or "Policy", history=body, target=fmt(document_target(history), ctx.decimals))


def _as_list(ctx: PromptContext) -> PromptContext:
    return ctx if ctx.params_style == "list" else replace(ctx, params_style="list")


def continuation_grammar(D: int, history: Sequence[EncodedEntry] = (), ctx: PromptContext | None = None) -> str:
    """GBNF for the continuation: ``0:`` value ``,1:`` value ... ``,D-1:`` value ``]`` (the labels
    are fixed text; the model writes only the values).

    With ``history`` (the shown entries) and ``ctx``, the grammar fits the encoded scale of each
    coordinate: a value is written as the prompt writes numbers (in ``ctx.numbers``, the number
    format: integers on the grid, else ``ctx.param_digits`` significant digits with at most
    ``ctx.decimals`` decimals), with at most as many integer digits
    as the widest value the prompt prints at that coordinate. So a proposal can go up to ten
    times past the shown values, but not write a coordinate whose values are in the tens with
    three integer digits, nor spend tokens on digits the history never shows. It is built only
    from the printed (encoded) history, which the model reads anyway. Without a history: at most
    three digits on each side of the point. No whitespace, no exponent.
    """
    if D < 1:
        raise ValueError(f"D must be >= 1, got {D}")
    rules: dict[str, str] = {}
    if not history or ctx is None:
        names = ["num"] * D
        rules["num"] = "num ::= " + (ctx.numbers if ctx is not None else DECIMAL).number_rule()
    else:
        lst = _as_list(ctx)
        widest = [1] * D
        for e in history:
            if len(e.params) != D:
                raise ValueError(f"history entry {e.index} has {len(e.params)} parameters, expected {D}")
            for j, tok in enumerate(params_text(lst, e.params).strip("[]").split(",")):
                widest[j] = max(widest[j], len(tok.lstrip("-").split(".")[0]))
        names = []
        for w in widest:
            name = f"w{w}"
            if name not in rules:
                alts = [_magnitude(k, ctx) for k in range(w + 1)]
                rules[name] = f'{name} ::= "-"? ({" | ".join(alts)})'
            names.append(name)
    items = [f'"{"," if j else ""}{j}{LABEL}" {n}' if is_labelled(ctx, j) else f'"," {n}' for j, n in enumerate(names)]
    root = "root ::= " + " ".join(items) + ' "]"'
    return "\n".join([root, *rules.values()]) + "\n"


def _magnitude(k: int, ctx: PromptContext) -> str:
    """GBNF for a number with ``k`` integer digits (0: below 1) as the list form prints it."""
    digits, decimals = ctx.param_sig_digits, ctx.param_decimals  # the number format's (wire.numbers)
    fixed = digits <= 0
    if k == 0:
        dec, ints = decimals, '"0"'
    else:
        dec = decimals if fixed else max(0, min(decimals, digits - k))
        ints = " ".join(["[1-9]"] + ["[0-9]"] * (k - 1))
    frac = f' ("." {" ".join(["[0-9]"] + ["[0-9]?"] * (dec - 1))})?' if dec > 0 else ""
    return ints + frac
