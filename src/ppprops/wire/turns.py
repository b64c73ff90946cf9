"""The messages of a request: the prompt, and after an unusable answer the correction turns.

One rule, used by the proposer to build requests and by the audit to rebuild them:

- the first request of an iteration is the prompt as one user message;
- after an answer that cannot be used, the next request repeats the prompt, the answer's final
  text (``final_text``: no reasoning, no markup, which some chat templates refuse in an
  assistant turn; at most ``ECHO_CHARS`` characters) as the assistant turn, and a user turn that
  says what was wrong (``build_correction``). With no final text to repeat, the correction
  follows the prompt inside the one user message (templates such as Gemma's refuse two user
  turns in a row).

What was wrong is ``read_answer``'s detail, or, for an answer that only repeats a policy of the
history shown (at the precision the prompt printed it), ``REPEATS_HISTORY``. Only provider text
(the echo) and public template text are added to the prompt here. The document form
(``wire.document``) has no correction turns: an unusable continuation (``judge_continuation``)
is asked again with the same document. Standard library only.
"""

from __future__ import annotations

from collections.abc import Sequence

from .document import OPENING
from .encoded import EncodedEntry, PromptContext
from .parse import ParseResult, final_text, read_answer, read_continuation
from .prompt import build_correction, params_text

ECHO_CHARS = 2000  # longest final text repeated back to the model in a correction
REPEATS_HISTORY = "those params are a policy already in the history; propose a new one"

Messages = list[dict[str, str]]


def prompt_messages(prompt: str) -> Messages:
    """The first request of an iteration: the prompt as the one user message."""
    return [{"role": "user", "content": prompt}]


def echo_text(content: str | None) -> str:
    """The part of an answer repeated to the model in a correction: its final text, clipped and
    stripped (empty when the answer had no final text)."""
    return final_text(content)[:ECHO_CHARS].strip()


def correction_messages(prompt: str, content: str | None, detail: str, D: int) -> Messages:
    """The request after an unusable answer ``content`` (the provider's message content as
    received), whose fault is ``detail`` (``ParseResult.detail`` or ``REPEATS_HISTORY``); ``D``
    numbers are asked for. Three turns [prompt, echo, correction], or one user turn
    ``prompt + "\\n\\n" + correction`` when there is nothing to echo."""
    correction = build_correction(detail, D)
    echo = echo_text(content)
    if not echo:
        return [{"role": "user", "content": f"{prompt}\n\n{correction}"}]
    return [
        {"role": "user", "content": prompt},
        {"role": "assistant", "content": echo},
        {"role": "user", "content": correction},
    ]


def repeats_history(ctx: PromptContext, values: Sequence[float], shown: Sequence[EncodedEntry]) -> bool:
    """True if ``values`` print (``params_text``) exactly as a parameter vector of ``shown`` does."""
    printed = params_text(ctx, tuple(values))
    return any(printed == params_text(ctx, e.params) for e in shown)


def judge_answer(content: str | None, reasoning: str | None, ctx: PromptContext, shown: Sequence[EncodedEntry], *,
                 finish_reason: str | None = None) -> ParseResult:
    """The proposal in an answer (``read_answer``), refused with ``repeats_history`` (detail
    ``REPEATS_HISTORY``) when it is a policy of the history ``shown`` in the prompt. Never raises."""
    result = read_answer(content, reasoning, ctx.D, finish_reason=finish_reason)
    if result.values is not None and repeats_history(ctx, result.values, shown):
        return ParseResult(None, "repeats_history", REPEATS_HISTORY, result.source)
    return result


def judge_continuation(content: str | None, ctx: PromptContext, shown: Sequence[EncodedEntry], *,
                       finish_reason: str | None = None) -> ParseResult:
    """The document form's counterpart of ``judge_answer``: the proposal in a continuation of the
    open list (``read_continuation``), refused the same way when it repeats the history ``shown``.
    A document request has no correction turns: it is asked again as it was (``LLMProposer``)."""
    result = read_continuation(content, ctx.D, opening=OPENING, finish_reason=finish_reason)
    if result.values is not None and repeats_history(ctx, result.values, shown):
        return ParseResult(None, "repeats_history", REPEATS_HISTORY, result.source)
    return result
