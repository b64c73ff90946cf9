"""Prompt forms: each form owns its request end to end.

A form is one object that writes its prompt, builds every request of an iteration (the payload,
the sampling fields, the answer's budget and constraint, the public decisions it took), reads an
answer into a proposal, and says how the audit reads its recorded requests back (the entries it
prints, the numbers it derives from them, the decisions it may record). The proposer asks it for
requests; the transport (``ppprops.llm``) turns a ``FormRequest`` into a request body without
knowing any form; the audit looks up the form each call was recorded under (``FORMS``) and asks it
for the request it would have built. So a new request field is a change to one form here, and the
proposer, the client, the store and the audit carry it as they are.

``FORMS`` holds the built-in forms by name: ``chat`` (the paper's instruction prompt, to a
chat-completions endpoint, with correction turns after an unusable answer), ``document`` (the
history as a document for a base model to continue, to a completions endpoint, asked again on an
unusable answer: ``wire.document``) and ``r2po-critic`` (R2PO's critic prompt, sent and corrected
as the chat form). Standard library only, like the rest of ``ppprops.wire``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from .document import (
    OPENING,
    build_document,
    continuation_grammar,
    document_entry,
    document_sampling,
    document_target,
    document_temperature,
)
from .encoded import EncodedEntry, PromptContext
from .names import CHAT_FORM, CRITIC_FORM, DOCUMENT_FORM
from .numbers import DECIMAL, NumberFormat
from .parse import ParseResult, read_answer, read_continuation
from .prompt import build_prompt, history_entry, template
from .transcript import ShownEntry, history_entries, open_target
from .turns import REPEATS_HISTORY, correction_messages, judge_answer, judge_continuation, prompt_messages

ENDPOINT_CHAT = "chat"  # /chat/completions: a list of messages
ENDPOINT_COMPLETIONS = "completions"  # /completions: one raw prompt, continued
CHAT_TEMPERATURE = 1.0  # the chat form's sampling temperature when --temperature is not set
# The document form's retry after a continuation that copied an entry of the history: llama.cpp's
# repeat penalty (over its last 64 tokens, which end the document with the best entries) makes the
# copied tokens less likely to come again.
REPEAT_PENALTY = 1.3


def params_schema(D: int, numbers: NumberFormat = DECIMAL) -> dict[str, Any]:
    """The JSON schema of a chat answer: an object with ``params``, an array of exactly ``D`` numbers
    (integers in the grid format)."""
    item = "integer" if numbers.integers else "number"
    return {
        "type": "object",
        "properties": {"params": {"type": "array", "items": {"type": item}, "minItems": D, "maxItems": D}},
        "required": ["params"],
        "additionalProperties": False,
    }


def params_grammar(D: int, numbers: NumberFormat = DECIMAL) -> str:
    """GBNF for ``{"params": [n, ...]}`` with exactly D numbers of the format ``numbers`` (plain
    decimals, or integers on the grid: ``wire.numbers.NumberFormat.number_rule``) and no free whitespace.

    llama.cpp's JSON-schema grammar lets small models pad with whitespace until the token limit;
    this one cannot, which keeps answers short and always parseable.
    """
    rest = f' ("," ws num){{{D - 1}}}' if D > 1 else ""
    return (
        f'root ::= "{{\\"params\\": [" num{rest} "]}}"\n'
        'ws ::= " "?\n'
        f"num ::= {numbers.number_rule()}\n"
    )


def answer_budget(D: int, *, labels: bool = False) -> int:
    """Tokens an answer of ``D`` numbers needs, before any room for reasoning or explanation.

    Some tokenizers (Gemma's) spend one token per digit, so ``-12.99, `` can take 7 tokens; 8 per
    number plus 24 for the frame leaves a margin. With ``labels`` (the document form's ``0:v,1:v,...]``)
    each value also carries its index and a colon, a token per character on Gemma: at least
    ``24 + sum over j of (digits of j + 7)`` (104 on CartPole as without labels, 4,504 at D = 459).
    """
    answer = 24 + 8 * D
    if labels:
        answer = max(answer, 24 + sum(len(str(j)) + 7 for j in range(D)))
    return answer


@dataclass(frozen=True)
class FormRequest:
    """One request a form asks the transport to send; the transport adds the endpoint's own fields.

    ``endpoint`` is ``chat`` (``messages``, to /chat/completions) or ``completions`` (``prompt``, to
    /completions); ``D`` numbers are asked for, in LLM ``iteration`` (0-based), ``attempt`` (0, or a
    retry after an unusable answer). ``sampling`` are request fields the form chooses (temperature
    first, then any other sampling field such as ``top_p``), each sent as it is until the endpoint
    refuses it. ``answer_tokens`` is the answer's budget before room for reasoning; ``explains``
    says an instruction-tuned model may write a short explanation first (room is added where nothing
    constrains the answer). The answer's constraint: ``json_schema`` (sent as ``response_format``
    under ``--structured json_schema``), ``grammar`` (GBNF, sent to servers that take grammars, and
    under ``--structured auto`` to any server when the form has no schema), ``stop`` (sequences
    that end the answer on servers that may not enforce the grammar). ``decisions`` are the public
    choices the form made, recorded with the call for the audit.
    """

    form: str
    endpoint: str
    D: int
    iteration: int = 0
    attempt: int = 0
    messages: tuple[Mapping[str, str], ...] | None = None
    prompt: str | None = None
    sampling: Mapping[str, Any] = field(default_factory=dict)
    answer_tokens: int = 0
    explains: bool = False
    json_schema: Mapping[str, Any] | None = None
    grammar: str | None = None
    stop: tuple[str, ...] = ()
    decisions: Mapping[str, Any] = field(default_factory=dict)

    @property
    def payload(self) -> dict[str, Any]:
        """The request body's payload field: ``{"messages": [...]}`` or ``{"prompt": "..."}``."""
        if self.endpoint == ENDPOINT_COMPLETIONS:
            return {"prompt": self.prompt}
        return {"messages": [dict(m) for m in self.messages or ()]}

    @property
    def prompt_chars(self) -> int:
        """Characters of prompt text sent (the document, or every message's content)."""
        if self.endpoint == ENDPOINT_COMPLETIONS:
            return len(self.prompt or "")
        return sum(len(m["content"]) for m in self.messages or ())


@dataclass(frozen=True)
class Derived:
    """A number a form prints that it computes from the shown (encoded) entries, not copied from
    one: where it is in the prompt (``offset``, the printed ``token``), the value the form computes,
    and how the audit names a mismatch (``kind``, ``detail``)."""

    offset: int
    token: str
    value: float | None
    kind: str
    detail: str


class PromptForm:
    """The chat form, and the base of the others: the paper's instruction prompt as one user
    message to a chat-completions endpoint; an unusable answer gets correction turns
    (``wire.turns``). Its answer is ``{"params": [...]}`` under a JSON schema or a grammar.

    Attributes:
        name: recorded with every call of the form (the audit looks the form up by it).
        endpoint: where its requests go.
        entry_templates: the templates its history entries are printed with (``wire.transcript``).
        default_digits: significant digits of a parameter when ``--param-digits`` is not given.
        shows_feedback: its entries print reward components and diagnostics.
        describes_encoding: its prompt says in words how parameters and rewards are encoded.
    """

    name = CHAT_FORM
    endpoint = ENDPOINT_CHAT
    entry_templates: tuple[str, ...] = ("history_entry", "history_entry_indexed")
    default_digits = 3
    shows_feedback = True
    describes_encoding = True

    def answer_tokens(self, D: int) -> int:
        """Tokens an answer of ``D`` numbers in this form needs (``answer_budget``: unlabelled values)."""
        return answer_budget(D)

    def prompt(self, ctx: PromptContext, shown: Sequence[EncodedEntry]) -> str:
        """The prompt of one iteration from the public context and the shown history (lowest return first)."""
        return build_prompt(ctx, shown)

    def request(self, prompt: str, *, ctx: PromptContext, shown: Sequence[EncodedEntry], iteration: int, attempt: int,
                previous: str | None = None, detail: str = "", temperature: float | None = None, stalled: int = 0) -> FormRequest:
        """Attempt ``attempt`` of iteration ``iteration``: the prompt, or after the unusable answer
        ``previous`` (its content) whose fault is ``detail``, the correction turns, at
        ``temperature`` (``--temperature``; None: ``CHAT_TEMPERATURE``). ``stalled`` (LLM iterations
        in a row that did not raise the best shown return) is for forms that explore; unused here."""
        if attempt == 0:
            messages, decisions = prompt_messages(prompt), {}
        else:
            messages, decisions = correction_messages(prompt, previous, detail, ctx.D), {"correction": detail}
        return FormRequest(self.name, self.endpoint, ctx.D, iteration, attempt, messages=tuple(messages),
                           sampling={"temperature": CHAT_TEMPERATURE if temperature is None else temperature},
                           answer_tokens=self.answer_tokens(ctx.D), explains=True, json_schema=params_schema(ctx.D, ctx.numbers),
                           grammar=params_grammar(ctx.D, ctx.numbers), decisions=decisions)

    def judge(self, content: str | None, reasoning: str | None, ctx: PromptContext, shown: Sequence[EncodedEntry], *,
              finish_reason: str | None = None) -> ParseResult:
        """The proposal in an answer, refused when it repeats an entry of ``shown`` (``wire.turns.judge_answer``). Never raises."""
        return judge_answer(content, reasoning, ctx, shown, finish_reason=finish_reason)

    def read(self, content: str | None, D: int, *, reasoning: str | None = None, finish_reason: str | None = None) -> ParseResult:
        """The ``D`` numbers in an answer of this form, without the history check (``wire.parse.read_answer``)."""
        return read_answer(content, reasoning, D, finish_reason=finish_reason)

    def entries(self, text: str) -> list[ShownEntry]:
        """The history entries printed in a prompt of this form, in order."""
        return history_entries(text, self.entry_templates)

    def render_entry(self, ctx: PromptContext, e: EncodedEntry) -> str:
        """One history entry as this form prints it (the audit compares each printed entry with it)."""
        return history_entry(ctx, e)

    def derived(self, text: str, shown: Sequence[EncodedEntry]) -> list[Derived]:
        """The numbers of ``text`` this form computes from the shown entries (none for the chat form)."""
        return []

    def check_decisions(self, decisions: Mapping[str, Any], ctx: PromptContext, shown: Sequence[EncodedEntry], *,
                        iteration: int, attempt: int, temperature: float | None, stalled: int = 0) -> list[str]:
        """What is wrong with recorded ``decisions`` (empty: each is one the form makes from public
        values). The audit passes ``stalled`` as it counts it from the shown returns; a decision that
        is not derivable from the prompt and the public settings could carry something else."""
        extra = sorted(set(decisions) - {"correction"})
        return [f"unknown decision {k!r}" for k in extra]


class DocumentForm(PromptForm):
    """The document form (``wire.document``): the history as a document for a base model to
    continue, to a completions endpoint, under a grammar fitted to the shown history, at the
    form's temperature schedule (``document_temperature``; untruncated sampling when the search is
    stuck). An unusable continuation is asked again with the same document (a retry raises the
    temperature); there is no conversation. Its entries show returns only, and its prompt does
    not describe the encoding."""

    name = DOCUMENT_FORM
    endpoint = ENDPOINT_COMPLETIONS
    entry_templates = ("document_entry",)
    default_digits = 2
    shows_feedback = False
    describes_encoding = False

    def answer_tokens(self, D: int) -> int:
        """Tokens a continuation of ``D`` labelled values (``0:v,1:v,...]``) needs (``answer_budget``)."""
        return answer_budget(D, labels=True)

    def prompt(self, ctx: PromptContext, shown: Sequence[EncodedEntry]) -> str:
        """The document, ending inside the open block (target return above the best shown)."""
        return build_document(ctx, shown)

    def request(self, prompt: str, *, ctx: PromptContext, shown: Sequence[EncodedEntry], iteration: int, attempt: int,
                previous: str | None = None, detail: str = "", temperature: float | None = None, stalled: int = 0) -> FormRequest:
        """The same document at every attempt, with the continuation grammar, the temperature
        ``document_temperature(iteration, attempt, temperature, stalled)`` and, when exploring, the
        untruncated sampling of ``document_sampling``; a retry after a continuation that repeated an
        entry of the history (``detail``) also carries ``REPEAT_PENALTY``; the stop sequence ``]``
        ends the list on a server that does not hold the model to the grammar."""
        t = document_temperature(iteration, attempt, temperature, stalled)
        decisions = {"temperature": t, "target": document_target(shown) if shown else None, "stalled": stalled}
        sampling: dict[str, float] = {"temperature": t, **document_sampling(stalled, temperature)}
        if attempt > 0 and detail == REPEATS_HISTORY:
            sampling["repeat_penalty"] = REPEAT_PENALTY
        return FormRequest(self.name, self.endpoint, ctx.D, iteration, attempt, prompt=prompt, sampling=sampling,
                           answer_tokens=self.answer_tokens(ctx.D), grammar=continuation_grammar(ctx.D, shown, ctx),
                           stop=("]",), decisions=decisions)

    def judge(self, content: str | None, reasoning: str | None, ctx: PromptContext, shown: Sequence[EncodedEntry], *,
              finish_reason: str | None = None) -> ParseResult:
        """The proposal in a continuation of the open list (``wire.turns.judge_continuation``)."""
        return judge_continuation(content, ctx, shown, finish_reason=finish_reason)

    def read(self, content: str | None, D: int, *, reasoning: str | None = None, finish_reason: str | None = None) -> ParseResult:
        """The ``D`` numbers in a continuation (``wire.parse.read_continuation``)."""
        return read_continuation(content, D, opening=OPENING, finish_reason=finish_reason)

    def render_entry(self, ctx: PromptContext, e: EncodedEntry) -> str:
        """One entry as the document prints it (``wire.document.document_entry``)."""
        return document_entry(ctx, e)

    def derived(self, text: str, shown: Sequence[EncodedEntry]) -> list[Derived]:
        """The open block's return: ``document_target`` of the shown entries (None when the
        prompt does not end in an open block, or no entry was verified)."""
        found = open_target(text)
        if found is None:
            return [Derived(len(text), "", None, "target", "a document prompt that does not end in an open block")]
        at, tok = found
        value = document_target(shown) if shown else None
        return [Derived(at, tok, value, "target", "the open block's return is not the target computed from the shown encoded returns")]

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
    evidence rather than from a history (the proposer builds it with
    ``wire.r2po.build_critic_prompt``); sent and corrected as the chat form is."""

    name = CRITIC_FORM


def recorded_form(body: str) -> str:
    """The form of a request recorded before each call named its form (run stores of schema 4 and
    older): a completions body (a ``prompt``) is the document form's; a chat body whose first
    message opens with R2PO's critic template is the critic's; any other, the chat form's. Used
    once, when such a store is migrated."""
    import json

    try:
        doc = json.loads(body)
    except ValueError:
        return CHAT.name
    if not isinstance(doc, dict):
        return CHAT.name
    if isinstance(doc.get("prompt"), str) and "messages" not in doc:
        return DOCUMENT.name
    messages = doc.get("messages")
    first = messages[0].get("content") if isinstance(messages, list) and messages and isinstance(messages[0], dict) else None
    head = template("r2po_critic").template.split("$", 1)[0]
    return CRITIC.name if isinstance(first, str) and first.startswith(head) else CHAT.name


CHAT, DOCUMENT, CRITIC = PromptForm(), DocumentForm(), CriticForm()
FORMS: dict[str, PromptForm] = {f.name: f for f in (CHAT, DOCUMENT, CRITIC)}
