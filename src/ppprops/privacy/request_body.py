"""The audit's reader of request bodies (``privacy.audit``): every byte of each recorded call.

``BodyReader`` reads the calls in the order they were sent, as the client would have built them:
it keeps what the client knew at each call (the usable answer of each attempt, the prompt context
of each form, the stall count of every prefix of the candidates), rebuilds the request each call's
form makes from public values (``wire.forms``) and compares the recorded body with it, field by
field and message by message. What it cannot account for goes to the auditor (``Checks``): the
history entries it finds are checked there (``entry``), text the templates do not produce is read
there for raw values (``free``, ``spans``), and every finding is counted there.
"""
from __future__ import annotations

import bisect
import json
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from .. import seeding
from ..client.codec import Codec
from ..client.secrets import Secrets
from ..config import RunConfig
from ..methods import Mechanisms
from ..proposers.llm import StallCounter
from ..store import Candidate
from ..tasks.base import Task
from ..wire.encoded import EncodedEntry
from ..wire.forms import CHAT, CRITIC, ENDPOINT_COMPLETIONS, FORMS, FormRequest, PromptForm
from ..wire.transcript import ShownEntry
from ..wire.turns import REPEATS_HISTORY
from . import reconstruct as rc
from .requests import Request, message_text
from .tokens import renders, token_value

# Every top-level field the client may send in some state of its request shape (``RequestShape``),
# besides the sampling fields the forms choose; and the fields the shape alone decides.
SENT_FIELDS = frozenset({"model", "messages", "prompt", "temperature", "max_tokens", "max_completion_tokens", "seed", "reasoning_effort",
                         "response_format", "grammar", "stop", "top_p", "min_p", "top_k"})
_SHAPE_FIELDS = frozenset({"model", "max_tokens", "max_completion_tokens", "seed", "reasoning_effort"})


class Checks(Protocol):
    """What the body reader uses of the auditor: the run, its candidates, and its checks of what was printed."""

    config: RunConfig
    mech: Mechanisms
    task: Task
    codec: Codec
    secrets: Secrets | None
    cands: list[Candidate]
    shown: dict[int, Candidate]  # candidates that appeared in some request
    replay: rc.ClientReplay  # the client's request shape, replayed on the recorded exchanges
    problems: int  # occurrences of findings other than channels so far

    def finding(self, severity: str, kind: str, detail: str, where: str, *, by_design: bool = False) -> None:
        """Count one occurrence of a finding at ``where``."""

    def free(self, value: object, why: str, where: str) -> None:
        """Read every number in ``value`` against every raw value; unverified (``why``) when none is raw."""

    def spans(self, expected: str, text: str, flagged: list[tuple[int, int]], where: str, what: str = ...) -> None:
        """Read every stretch of ``text`` that the client does not produce (``expected``)."""

    def entry(self, req: Request, k: int, e: ShownEntry) -> Candidate | None:
        """Check one shown entry; returns the candidate it shows, or None if it matches none."""

    def match(self, vals: np.ndarray, tols: np.ndarray, shown: ShownEntry | None = ...) -> tuple[int | None, str]:
        """The candidate whose parameters (encoded, else raw) the printed ``vals`` show, and which."""

    def prose(self, req: Request, text: str, entries: list[ShownEntry], skips: Sequence[int] = ...) -> None:
        """Read the numbers outside the history entries of a prompt."""


class BodyReader:
    """Reads each recorded call's body (``body``) against the request the client builds for it.

    Calls must be read in the order they were sent: the client's state (the previous attempt's
    answer, the endpoint's adaptations) follows them.
    """

    def __init__(self, audit: Checks) -> None:
        self.audit = audit
        self._rebuilt: dict[str, rc.Rebuilt] = {}  # per prompt form: its context, and each candidate's entry built once
        self.rebuilt = self._rebuilt_for(FORMS[audit.config.form])  # that of the call being read (``body``)
        self.ctx = self.rebuilt.ctx
        self.answered: dict[tuple[int, int], dict[str, Any]] = {}  # (iteration, attempt) -> its latest usable answer
        counter = StallCounter()  # stall_count of every prefix of the candidates, counted once
        self._stalls = [0]
        for c in audit.cands:
            counter.tell(c)
            self._stalls.append(counter.count)

    def _rebuilt_for(self, form: PromptForm) -> rc.Rebuilt:
        """The public prompt context of ``form`` (``reconstruct.context``) and its entries, built once per run."""
        if form.name not in self._rebuilt:
            context = rc.context(self.audit.task, self.audit.config, self.audit.codec, form)
            self._rebuilt[form.name] = rc.Rebuilt(self.audit.codec, context, form)
        return self._rebuilt[form.name]

    def _stall_count(self, n: int) -> int:
        """``stall_count`` of the candidates numbered below ``n`` (the trials settled when a request
        at trial ``n`` was built: failed trials are no candidates and never counted)."""
        return self._stalls[bisect.bisect_left([c.index for c in self.audit.cands], n)]

    def _round_start(self, iteration: int) -> int:
        """The trial number at which the round of LLM iteration ``iteration`` began: with
        ``--parallel`` P its P requests share the history told before the round."""
        parallel = max(1, int(getattr(self.audit.config, "parallel", 1)))
        return self.audit.config.warmup + (iteration // parallel) * parallel

    def body(self, row: dict[str, Any], req: Request) -> None:
        """One recorded call, read as the prompt form it was recorded under (``wire.forms.FORMS``):
        its payload (the messages or the document) rebuilt and compared (``messages``, ``prompt``),
        every other field compared with the body the client builds for the request the form makes
        from public values (``FormRequest``, through the replayed ``RequestShape``), and the
        decisions recorded with the call checked by the form."""
        where = req.where
        form = FORMS.get(str(row.get("form")))
        self.rebuilt = self._rebuilt_for(form or CHAT)
        self.ctx = self.rebuilt.ctx
        try:
            doc = json.loads(str(row["request"]))
        except json.JSONDecodeError:
            doc = None
        if form is None:
            self.audit.finding("unverified", "request", f"a call recorded under an unknown prompt form {row.get('form')!r}", where)
            self.audit.free(doc if doc is not None else str(row["request"]), "", where)
            self.audit.replay.observe(row, self._request(CHAT, req, []))
            return
        if not isinstance(doc, dict):
            self.audit.free(str(row["request"]), "a request body that is not a JSON object", where)
            self.audit.replay.observe(row, self._request(form, req, []))
            return
        key = "prompt" if form.endpoint == ENDPOINT_COMPLETIONS else "messages"
        shown: list[Candidate | None] = []
        if key not in doc:
            self.audit.finding("unverified", "request", f"a request without {key}", where)
        elif key == "messages":
            shown = self.messages(doc[key], req, form)
        elif isinstance(doc[key], str):
            shown = self.prompt(doc[key], req, form)
        else:
            self.audit.free(doc[key], f"a {form.name} prompt that is not a string", f"{where}, field {key}")
        verified = bool(shown) and all(c is not None for c in shown)
        entries = [self.rebuilt.entry(c) for c in shown if c is not None] if verified else []
        stalled = self._stall_count(self._round_start(req.iteration)) if self.audit.config.explore is not False else 0
        want = self._request(form, req, entries, stalled)
        expected = self.audit.replay.fields(want)  # what the client's request shape sends for it at this call
        decisions = row.get("decisions")
        if decisions is not None and verified:
            for problem in form.check_decisions(decisions, self.ctx, entries, iteration=req.iteration, attempt=req.attempt,
                                                temperature=self.audit.config.llm.temperature, stalled=stalled):
                self.audit.finding("unverified", "decisions", f"a recorded decision of the {form.name} form: {problem}", where)
        unrebuilt = "" if verified else " (the history it shows is not verified, so it cannot be rebuilt)"
        for name, value in doc.items():
            at = f"{where}, field {name}"
            if name == key:
                continue
            if name == "seed" and name in expected:
                self.seed(value, req)
            elif name in expected:
                if value != expected[name]:
                    self.audit.free(value, f"field {name} differs from what the client sends{'' if name in _SHAPE_FIELDS else unrebuilt}", at)
            elif name in SENT_FIELDS:
                self.audit.free(value, f"field {name}, which the client does not send at this point (its endpoint adaptations)", at)
            else:
                self.audit.free(value, f"field {name}, which the client never sends", at)
        missing = [k for k in expected if k not in doc]
        if missing:
            self.audit.finding("unverified", "request", f"a request without the field(s) {', '.join(missing)} the client sends", where)
        self.audit.replay.observe(row, want)
        if row.get("ok"):
            self.answered[(req.iteration, req.attempt)] = row

    def _request(self, form: PromptForm, req: Request, entries: list[EncodedEntry], stalled: int = 0) -> FormRequest:
        """The request ``form`` makes at this call from what the proposer had: the public context,
        the entries shown, the settings, the stall count and, on a retry, the previous attempt's
        answer and the form's verdict on it (its payload is a placeholder: the payload is compared
        by ``messages`` / ``prompt``)."""
        previous = self.answered.get((req.iteration, req.attempt - 1)) if req.attempt > 0 else None
        content, detail = None, ""
        if previous is not None:
            finish, _ = rc.response_facts(previous.get("response"))
            content = previous.get("content")
            detail = form.judge(content, previous.get("reasoning"), self.ctx, entries, finish_reason=finish).detail
        return form.request(rc.PROMPT_MARK, ctx=self.ctx, shown=entries, iteration=req.iteration, attempt=req.attempt,
                            previous=content, detail=detail, temperature=self.audit.config.llm.temperature, stalled=stalled)

    def seed(self, value: object, req: Request) -> None:
        """The request's sampling seed: the key-derived one (``Codec.sampling_seed``), else read for raw values."""
        at = f"{req.where}, field seed"
        if value is None:
            return
        if not isinstance(value, int) or isinstance(value, bool):
            self.audit.free(value, "field seed that is not an integer", at)
            return
        if value == seeding.llm_seed(self.audit.config.seed, req.iteration, req.attempt):
            self.audit.finding("channel", "run_seed", "the request's sampling seed derives from the run seed (runs made before "
                         "sampling seeds were keyed by the secrets): trying run seeds finds it", at)
            return
        if self.audit.secrets is not None and value != self.audit.codec.sampling_seed(self.audit.config.seed, req.iteration, req.attempt):
            self.audit.free(value, "field seed that is not the key-derived sampling seed", at)
        elif self.audit.secrets is None:
            self.audit.free(value, "", at)  # not verifiable without the key file: still read for raw values

    def messages(self, value: object, req: Request, form: PromptForm) -> list[Candidate | None]:
        """The messages of a chat-endpoint form, rebuilt as the form builds them (``form.request``):
        the prompt, or after an unusable answer the prompt, that answer's final text and the
        correction (or prompt and correction in one user turn). Every message is compared with its
        rebuilt text and what differs is read; messages in any other arrangement are read whole.
        Returns the candidates the prompt shows."""
        if not isinstance(value, list):
            self.audit.free(value, "messages that are not a list", f"{req.where}, messages")
            return []
        sent: list[tuple[int, object, str]] = []  # (position, role, text) of every readable message
        for i, m in enumerate(value):
            at = f"{req.where}, message {i + 1}"
            if not isinstance(m, dict):
                self.audit.free(m, "a message that is not an object", at)
                continue
            role, content = m.get("role"), m.get("content")
            for k, v in m.items():
                if k not in ("role", "content"):
                    self.audit.free(v, f"message field {k}, which the client never sends", at)
            if isinstance(content, list):
                self.audit.finding("unverified", "request", "message content sent as a list of parts (the client sends strings)", at)
                content = message_text(content)
            elif not isinstance(content, str):
                self.audit.free(content, "message content that is not a string", at)
                continue
            sent.append((i, role, content))
        want, repeated = self._turns(form, req)
        if want is None or len(sent) != len(value) or [r for _, r, _ in sent] != [m["role"] for m in want]:
            return self._unexpected_turns(sent, req, form, want is None)
        shown: list[Candidate | None] = []
        for (i, _, text), message in zip(sent, want, strict=True):
            at = f"{req.where}, message {i + 1}"
            if rc.PROMPT_MARK in message["content"]:
                before, after = message["content"].split(rc.PROMPT_MARK)
                shown = self.prompt(text, req, form, before, after)
            elif message["role"] == "assistant":
                self.audit.spans(message["content"], text, [], at, "an assistant turn that is not the provider's own final text")
            else:
                self.audit.spans(message["content"], text, [], at, "text the correction template does not produce")
        if repeated is not None:
            finish, _ = rc.response_facts(repeated.get("response"))
            entries = [self.rebuilt.entry(c) for c in shown if c is not None]
            verdict = form.judge(repeated.get("content"), repeated.get("reasoning"), self.ctx, entries, finish_reason=finish)
            if verdict.error != "repeats_history":
                self.audit.finding("unverified", "request", "a correction after an answer the client takes (it repeats no policy "
                             "of the history shown)", req.where)
        return shown

    def _turns(self, form: PromptForm, req: Request) -> tuple[list[Mapping[str, str]] | None, dict[str, Any] | None]:
        """The messages ``form`` sends at this call, with ``rc.PROMPT_MARK`` where the prompt goes:
        the prompt, or after the recorded answer of the previous attempt the correction with the fault
        ``form.read`` finds in it, or ``REPEATS_HISTORY`` when it holds a proposal (then that answer
        is returned too: the correction is the client's only if it repeats the history shown, which
        the caller checks once it knows the history). None when that answer is not recorded."""
        previous = self.answered.get((req.iteration, req.attempt - 1)) if req.attempt > 0 else None
        if req.attempt > 0 and previous is None:
            return None, None
        detail, repeated = "", None
        if previous is not None:
            finish, _ = rc.response_facts(previous.get("response"))
            result = form.read(previous.get("content"), self.audit.task.D, reasoning=previous.get("reasoning"), finish_reason=finish)
            detail, repeated = (REPEATS_HISTORY, previous) if result.ok else (result.detail, None)
        req_form = form.request(rc.PROMPT_MARK, ctx=self.ctx, shown=[], iteration=req.iteration, attempt=req.attempt,
                                previous=None if previous is None else previous.get("content"), detail=detail)
        return list(req_form.messages or ()), repeated

    def _unexpected_turns(self, sent: list[tuple[int, object, str]], req: Request, form: PromptForm,
                          unknown: bool) -> list[Candidate | None]:
        """Messages not in the form's arrangement: the first user message is read as the prompt,
        every other message whole, numbers and all."""
        if unknown:
            self.audit.finding("unverified", "request", "a correction after an answer that is not recorded", req.where)
        prompt_seen = False
        shown: list[Candidate | None] = []
        for i, role, text in sent:
            if role == "user" and not prompt_seen:
                prompt_seen = True
                shown = self.prompt(text, req, form)
            else:
                self.audit.free(text, f"a {role} message at position {i + 1}, which the client does not send there",
                          f"{req.where}, message {i + 1}")
        return shown

    def prompt(self, text: str, req: Request, form: PromptForm, before: str = "", after: str = "") -> list[Candidate | None]:
        """A prompt of ``form`` (the chat prompt in a message, or a document), with ``before``/``after``
        what the client puts around it in the same message: each history entry the form prints
        matched and checked (``entry``), each number the form derives from them checked
        (``form.derived``), the rest read as prose, and the whole rebuilt from the shown candidates
        (``reconstruct.prompt_spans``). R2PO's critic prompt is checked by ``critic``. Returns the
        candidates shown (None for an entry that matches none)."""
        if form is CRITIC:
            self.critic(text, req, before, after)
            return []
        inner = text[len(before):len(text) - len(after)] if text.startswith(before) and text.endswith(after) \
            and len(text) >= len(before) + len(after) else text
        # the entries ``parse_request`` read in the same text with the same form, else read here
        entries = list(req.entries) if text == req.text and form.name == req.form else form.entries(text)
        shown: list[Candidate | None] = []
        flagged: list[tuple[int, int]] = []
        for k, e in enumerate(entries):
            before_count = self.audit.problems
            c = self.audit.entry(req, k, e)
            shown.append(c)
            if c is None or self.audit.problems > before_count:
                flagged.append((e.start, e.end))
        rebuilt = self._rebuilt_for(form)
        verified = [rebuilt.entry(c) for c in shown if c is not None] if all(c is not None for c in shown) else []
        skips = []
        for d in form.derived(text, verified):
            parsed = token_value(d.token) if d.token else None
            if d.value is not None and parsed is not None and renders(d.value, *parsed):
                skips.append(d.offset)  # derived from the shown encoded values, as the form computes it
            else:
                self.audit.finding("unverified", d.kind, d.detail, f"{req.where}, prose at character {d.offset}" if d.token else req.where)
        self.audit.prose(req, inner, entries if inner == text else form.entries(inner), skips)
        for a, b in rc.prompt_spans(rebuilt, text, entries, shown, before, after):
            if any(s <= a and b <= e for s, e in flagged) or any(a <= at < b for at in skips):
                continue  # inside an entry already reported, or a derived number checked above
            self.audit.free(text[a:b], f"text the {form.name} form's templates do not produce: {text[a:b][:60]!r}", f"{req.where}, character {a}")
        return shown

    def critic(self, text: str, req: Request, before: str = "", after: str = "") -> None:
        """R2PO's critic prompt: the candidate whose evidence it shows, matched by its printed parameters, and the
        rest of the prompt rebuilt from it (``reconstruct.expected_critic``)."""
        printed = rc.critic_params(text)
        c = None
        if printed is not None:
            toks = [token_value(t) for t in printed.strip("[]").split(",")]
            if toks and all(t is not None for t in toks):
                vals = np.array([t[0] for t in toks if t])
                tols = np.array([t[1] for t in toks if t])
                idx, _ = self.audit.match(vals, tols)
                c = self.audit.cands[idx] if idx is not None else None
        if c is None:
            self.audit.free(text, "a critic prompt whose candidate matches no evaluated candidate", req.where)
            return
        self.audit.shown[c.index] = c
        self.audit.finding("leak", "raw_trajectory", "raw states and the actions taken in them (R2PO's critic evidence)"
                     + ("" if not self.audit.mech.encode_params else "; beside encoded parameters, a least-squares fit gives A"),
                     req.where, by_design=not (self.audit.mech.encode_params or self.audit.mech.scale_rewards))
        self.audit.spans(before + rc.expected_critic(self.ctx, c, text) + after, text, [], req.where)
