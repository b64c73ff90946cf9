"""Prompt forms: each is one object that knows how its prompt is written, sent, read and checked.

A form is what the proposer asks it for and what the audit checks it against, so the two can
never disagree, and adding a form touches this module (and its templates), not the proposer or
the audit:

- ``prompt(ctx, shown)`` the prompt text of an iteration (from the public context and the encoded
  history shown, lowest return first);
- ``request(prompt, ...)`` one request of that iteration (attempt 0, or a retry after an unusable
  answer): the endpoint it goes to, the chat messages or the document, the grammar, the sampling
  temperature it chooses, and the public ``decisions`` recorded with the call (the audit reads them);
- ``judge(...)`` reads an answer into a proposal (``ParseResult``), refusing one that repeats an
  entry of the history shown;
- ``entries(text)`` / ``render_entry(ctx, e)`` read the shown entries back out of a recorded
  prompt and write one entry as the form does (the audit compares them).

``FORMS`` holds the built-in forms by name: ``chat`` (the paper's instruction prompt, chat
completions, correction turns), ``document`` (the history as a document for a base model to
continue, completions endpoint, asked again on an unusable answer: ``wire.document``) and
``r2po-critic`` (R2PO's critic prompt: chat completions with the rollout evidence,
``wire.r2po``). Standard library only, like the rest of ``ppprops.wire``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from .document import build_document, continuation_grammar, document_entry, document_sampling, document_target, document_temperature
from .encoded import EncodedEntry, PromptContext
from .parse import ParseResult
from .prompt import build_prompt, history_entry
from .transcript import ShownEntry, history_entries
from .turns import correction_messages, judge_answer, judge_continuation, prompt_messages

CHAT, COMPLETIONS = "chat", "completions"


@dataclass(frozen=True)
class FormRequest:
    """One request a form asks the client to send (the client adds the endpoint's own fields).

    ``endpoint`` is ``chat`` (``messages``, to /chat/completions) or ``completions`` (``prompt``,
    to /completions). ``grammar`` (GBNF), ``temperature`` and ``sampling`` (fields such as
    ``top_p``) are the form's choices for this request (None / empty: the client's defaults). ``decisions`` are the public choices the form made
    (temperature, the document's target return, ...), recorded with the call for the audit.
    """

    form: str
    endpoint: str
    messages: list[dict[str, str]] | None = None
    prompt: str | None = None
    grammar: str | None = None
    temperature: float | None = None
    sampling: Mapping[str, float] = field(default_factory=dict)  # more sampling fields (top_p, min_p, top_k), or none
    decisions: Mapping[str, Any] = field(default_factory=dict)


class PromptForm:
    """The chat form, and the base of the others: the paper's instruction prompt as one user
    message to a chat-completions endpoint; an unusable answer gets correction turns
    (``wire.turns``)."""

    name = CHAT
    endpoint = CHAT
    entry_form = "chat"  # how ``wire.transcript.history_entries`` reads its entries

    def prompt(self, ctx: PromptContext, shown: Sequence[EncodedEntry]) -> str:
        """The prompt of one iteration from the public context and the shown history."""
        return build_prompt(ctx, shown)

    def request(self, prompt: str, *, ctx: PromptContext, shown: Sequence[EncodedEntry], iteration: int, attempt: int,
                previous: str | None = None, detail: str = "", temperature: float | None = None, stalled: int = 0) -> FormRequest:
        """Attempt ``attempt`` of iteration ``iteration``: the prompt, or after the unusable answer
        ``previous`` (its content) whose fault is ``detail``, the correction turns. ``stalled``: LLM
        iterations in a row that did not raise the best shown return (forms that explore use it)."""
        if attempt == 0:
            return FormRequest(self.name, self.endpoint, messages=prompt_messages(prompt))
        return FormRequest(self.name, self.endpoint, messages=correction_messages(prompt, previous, detail, ctx.D),
                           decisions={"correction": detail})

    def judge(self, content: str | None, reasoning: str | None, ctx: PromptContext, shown: Sequence[EncodedEntry], *,
              finish_reason: str | None = None) -> ParseResult:
        """The proposal in an answer (``wire.turns.judge_answer``). Never raises."""
        return judge_answer(content, reasoning, ctx, shown, finish_reason=finish_reason)

    def entries(self, text: str) -> list[ShownEntry]:
        """The history entries printed in a recorded prompt of this form."""
        return history_entries(text, self.entry_form)

    def render_entry(self, ctx: PromptContext, e: EncodedEntry) -> str:
        """One history entry as this form prints it."""
        return history_entry(ctx, e)

    def check_decisions(self, decisions: Mapping[str, Any], ctx: PromptContext, shown: Sequence[EncodedEntry], *,
                        iteration: int, attempt: int, temperature: float | None, stalled: int = 0) -> list[str]:
        """What is wrong with recorded ``decisions`` (empty: each is one the form makes from public
        values). The audit calls this with ``stalled`` as it counts it from the shown returns; a
        decision that is not derivable from the prompt and the public settings could carry something else."""
        extra = sorted(set(decisions) - {"correction"})
        return [f"unknown decision {k!r}" for k in extra]


class DocumentForm(PromptForm):
    """The document form (``wire.document``): the history as a document for a base model to
    continue, to a completions endpoint, under a grammar fitted to the shown history, at the
    form's temperature schedule (``document_temperature``). An unusable continuation is asked
    again with the same document (a retry raises the temperature); there is no conversation."""

    name = "document"
    endpoint = COMPLETIONS
    entry_form = "document"

    def prompt(self, ctx: PromptContext, shown: Sequence[EncodedEntry]) -> str:
        """The document, ending inside the open block (target return above the best shown)."""
        return build_document(ctx, shown)

    def request(self, prompt: str, *, ctx: PromptContext, shown: Sequence[EncodedEntry], iteration: int, attempt: int,
                previous: str | None = None, detail: str = "", temperature: float | None = None, stalled: int = 0) -> FormRequest:
        """The same document at every attempt, with the continuation grammar, the temperature
        ``document_temperature(iteration, attempt, temperature, stalled)`` and, when exploring, the
        untruncated sampling of ``document_sampling`` (exploration when stuck)."""
        t = document_temperature(iteration, attempt, temperature, stalled)
        return FormRequest(self.name, self.endpoint, prompt=prompt, grammar=continuation_grammar(ctx.D, shown, ctx), temperature=t,
                           sampling=document_sampling(stalled, temperature),
                           decisions={"temperature": t, "target": document_target(shown), "stalled": stalled})

    def judge(self, content: str | None, reasoning: str | None, ctx: PromptContext, shown: Sequence[EncodedEntry], *,
              finish_reason: str | None = None) -> ParseResult:
        """The proposal in a continuation of the open list (``wire.turns.judge_continuation``)."""
        return judge_continuation(content, ctx, shown, finish_reason=finish_reason)

    def render_entry(self, ctx: PromptContext, e: EncodedEntry) -> str:
        """One entry as the document prints it (``wire.document.document_entry``)."""
        return document_entry(ctx, e)

    def check_decisions(self, decisions: Mapping[str, Any], ctx: PromptContext, shown: Sequence[EncodedEntry], *,
                        iteration: int, attempt: int, temperature: float | None, stalled: int = 0) -> list[str]:
        """The stall count must be the audit's own count, the temperature the schedule's for this
        iteration, attempt and stall count, and the target the one ``document_target`` computes from
        the shown (encoded) returns."""
        problems = [f"unknown decision {k!r}" for k in sorted(set(decisions) - {"temperature", "target", "stalled"})]
        if "stalled" in decisions and decisions["stalled"] != stalled:
            problems.append(f"stall count {decisions['stalled']!r} is not the {stalled} the shown returns give")
        if "temperature" in decisions and decisions["temperature"] != document_temperature(iteration, attempt, temperature, stalled):
            problems.append(f"temperature {decisions['temperature']!r} is not the schedule's for iteration {iteration}, attempt {attempt}")
        if "target" in decisions and shown and decisions["target"] != document_target(shown):
            problems.append(f"target {decisions['target']!r} is not computed from the shown returns")
        return problems


class CriticForm(PromptForm):
    """R2PO's critic (``wire.r2po``): a chat prompt built from one evaluated candidate's rollout
    evidence rather than from a history; its prompt comes from ``wire.r2po.build_critic_prompt``
    (the proposer builds it), and it is sent and corrected as the chat form is."""

    name = "r2po-critic"


FORMS: dict[str, PromptForm] = {f.name: f for f in (PromptForm(), DocumentForm(), CriticForm())}


def get_form(name: str) -> PromptForm:
    """The form called ``name``; ``KeyError`` listing the known forms for any other."""
    try:
        return FORMS[name]
    except KeyError:
        raise KeyError(f"unknown prompt form {name!r} (known: {', '.join(FORMS)})") from None
