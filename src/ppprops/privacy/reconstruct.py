"""What the client's own code sends, rebuilt from the store, so the audit can account for every byte.

A recorded prompt is compared with the prompt the templates produce from the public context and
the stored *encoded* values of the candidates it shows; whatever differs (text the templates do
not produce) is read number by number. The same is done for R2PO's critic prompt (its rollout
lines taken from the recording, since they are raw by design), for the correction turns (rebuilt
by ``wire.turns`` from the previous recorded answer, as the proposer builds them), and for every
top-level field of a request body (``ClientReplay``: the client's own ``RequestShape`` replayed on
the recorded exchanges, session by session).
"""

from __future__ import annotations

import difflib
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ..client.codec import Codec
from ..client.context import prompt_context
from ..client.hardening import codec_for
from ..client.secrets import Secrets
from ..config import LLMConfig, RunConfig
from ..llm.client import ADAPTABLE_KINDS, RequestShape, server_error
from ..tasks.base import Task
from ..values import Candidate
from ..wire import EncodedEntry, PromptContext
from ..wire.forms import FormRequest, PromptForm
from ..wire.r2po import Evidence, build_critic_prompt
from ..wire.transcript import ShownEntry

_ROLLOUT_LINE = re.compile(r"(\d+): \[([^\]]*)\] -> (.*)")


def client_codec(task: Task, config: RunConfig, secrets: Secrets | None) -> Codec:
    """The run's codec; without the key file, one with neutral secrets (enough for everything but a
    disclosed encoded optimum, which then cannot be verified)."""
    if secrets is None:
        secrets = Secrets(run_id="audit", a=np.ones(task.D), c=1.0)
    return codec_for(secrets, task, config.encoding)


def context(task: Task, config: RunConfig, codec: Codec, form: PromptForm) -> PromptContext:
    """The public prompt context of the run's prompts in ``form`` (``client.context.prompt_context``), as the proposer built it."""
    return prompt_context(task, config.prompt_settings(form.name), codec)


def _finite_components(components: Mapping[str, float]) -> dict[str, float]:
    return {k: float(v) for k, v in components.items() if math.isfinite(float(v))}


def _finite_diagnostics(diagnostics: Mapping[str, float | str]) -> dict[str, float | str]:
    return {k: (v if isinstance(v, str) or math.isfinite(float(v)) else "non-finite") for k, v in diagnostics.items()}


def entry_for(codec: Codec, ctx: PromptContext, c: Candidate) -> EncodedEntry:
    """The history entry the proposer builds for a candidate (``LLMProposer.tell``)."""
    fb = c.feedback_enc
    detailed = ctx.detailed_feedback
    return codec.entry(c.index, c.params_enc, fb.ret, _finite_components(fb.components) if detailed else {},
                       _finite_diagnostics(fb.diagnostics) if detailed else {})


class Rebuilt:
    """What the client builds for each candidate in one prompt form: its history entry
    (``entry_for``) and that entry as the form prints it, each built once per candidate (the
    audit reads the same candidates in many requests; a candidate's entry depends on nothing else).
    """

    def __init__(self, codec: Codec, ctx: PromptContext, form: PromptForm) -> None:
        self.codec, self.ctx, self.form = codec, ctx, form
        self._entries: dict[int, EncodedEntry] = {}
        self._texts: dict[int, str] = {}

    def entry(self, c: Candidate) -> EncodedEntry:
        """The history entry the proposer builds for ``c`` (``entry_for``)."""
        if c.index not in self._entries:
            self._entries[c.index] = entry_for(self.codec, self.ctx, c)
        return self._entries[c.index]

    def text(self, c: Candidate) -> str:
        """``c``'s entry as the form prints it (``PromptForm.render_entry``)."""
        if c.index not in self._texts:
            self._texts[c.index] = self.form.render_entry(self.ctx, self.entry(c))
        return self._texts[c.index]


def prompt_spans(rebuilt: Rebuilt, text: str, entries: list[ShownEntry], shown: list[Candidate | None], before: str = "",
                 after: str = "") -> list[tuple[int, int]]:
    """Spans of a recorded prompt of ``rebuilt.form`` that its templates do not produce from the shown candidates.

    The prose around the entries is compared as a skeleton (each entry one placeholder, so a
    missing or extra entry cannot shift the comparison); each matched entry is compared with the
    entry the form prints for its candidate. Unmatched entries are the caller's to report.
    ``before`` and ``after`` are text the client puts around the prompt in the same message (a
    correction after it, ``wire.turns``).
    """
    form, ctx = rebuilt.form, rebuilt.ctx
    built = [rebuilt.entry(c) if c is not None else _dummy(ctx) for c in shown]
    try:
        expected = before + form.prompt(ctx, built) + after
        expected_entries = form.entries(expected)
    except ValueError:  # a form that cannot write a prompt without an entry (the document form's target)
        expected, expected_entries = before + form.prompt(ctx, [_dummy(ctx)]) + after, []
    return _spans(text, entries, expected, expected_entries, [rebuilt.text(c) if c is not None else None for c in shown])


def _dummy(ctx: PromptContext) -> EncodedEntry:
    """A stand-in for a shown entry the audit could not match: one placeholder in the skeleton."""
    return EncodedEntry(index=-1, params=(0.0,) * ctx.D, ret=0.0)


def _spans(text: str, entries: list[ShownEntry], expected: str, expected_entries: list[ShownEntry],
           rendered: Sequence[str | None]) -> list[tuple[int, int]]:
    """The spans of ``text`` the expected prompt does not account for: the prose as a skeleton
    (each entry one placeholder), then each matched entry against its own printed text
    (``rendered``, None for an entry that matched no candidate)."""
    exp_skel, _ = _skeleton(expected, expected_entries)
    rec_skel, where = _skeleton(text, entries)
    out = [(where[a], where[min(b, len(where) - 1)] if b < len(where) else len(text)) for a, b in differing_spans(exp_skel, rec_skel)]
    for e, mine in zip(entries, rendered, strict=True):
        if mine is not None:
            out += [(e.start + a, e.start + b) for a, b in differing_spans(mine, text[e.start:e.end])]
    return sorted(out)


def _skeleton(text: str, entries: list[ShownEntry]) -> tuple[str, list[int]]:
    """The text with each entry replaced by one NUL, and the text offset of each skeleton character."""
    parts: list[str] = []
    where: list[int] = []
    pos = 0
    for e in entries:
        parts.append(text[pos:e.start])
        where.extend(range(pos, e.start))
        parts.append("\x00")
        where.append(e.start)
        pos = e.end
    parts.append(text[pos:])
    where.extend(range(pos, len(text)))
    return "".join(parts), where


def expected_critic(ctx: PromptContext, c: Candidate, recorded: str) -> str:
    """The critic prompt R2PO builds for candidate ``c``, with the rollout lines read from ``recorded``."""
    fb = c.feedback_enc
    rets = np.asarray(fb.episode_returns, dtype=float)
    if not len(rets):
        rets = np.array([fb.ret])
    order = np.argsort(rets, kind="stable")
    median_idx = int(order[(len(order) - 1) // 2])
    steps: list[tuple[tuple[float, ...], str]] = []
    for line in rollout_lines(recorded):
        m = _ROLLOUT_LINE.fullmatch(line)
        if m is None:
            continue
        try:
            state = tuple(float(x) for x in m.group(2).split(","))
        except ValueError:
            continue
        steps.append((state, m.group(3)))
    ev = Evidence(params=tuple(float(v) for v in c.params_enc),
                  returns=(float(rets.mean()), float(rets.std()), float(rets.min()), float(rets.max())),
                  episodes=len(rets), diagnostics=tuple(fb.diagnostics.items()), median_return=float(rets[median_idx]),
                  median_rollout=tuple(steps))
    return build_critic_prompt(ctx, ev)


def rollout_lines(text: str) -> list[str]:
    """The rollout section of a critic prompt, one string per line."""
    head = "one line per step as state -> action:\n"
    start = text.find(head)
    if start < 0:
        return []
    end = text.find("\n\n5. ", start)
    return text[start + len(head): end if end >= 0 else len(text)].split("\n")


def critic_params(text: str) -> str | None:
    """The printed parameter list (``[...]``, as text) of the candidate in an R2PO critic prompt; None if absent."""
    m = re.search(r"\n3\. The candidate:\nparams: (\[[^\]\n]*\])", text)
    return m.group(1) if m else None


# Where the prompt goes in the messages a form builds; the audit rebuilds the prompt itself.
PROMPT_MARK = "\x00prompt\x00"


def response_facts(response: str | None) -> tuple[str | None, int | None]:
    """(finish_reason, reasoning tokens) of a recorded response body, as the client read them."""
    try:
        doc = json.loads(response) if response else None
    except ValueError:
        return None, None
    if not isinstance(doc, dict):
        return None, None
    finish = None
    choices = doc.get("choices")
    if isinstance(choices, list) and choices and isinstance(choices[0], dict):
        f = choices[0].get("finish_reason")
        finish = f if isinstance(f, str) else None
    usage = doc.get("usage")
    details = usage.get("completion_tokens_details") if isinstance(usage, dict) else None
    tokens = details.get("reasoning_tokens") if isinstance(details, dict) else None
    return finish, tokens if isinstance(tokens, int) and not isinstance(tokens, bool) else None


# Status each adaptable error kind came with (``EndpointClient._attempt``; a 200 with an error body
# carries its code as the status, so the same).
_STATUS = {"bad_request": 400, "http_422": 422}
assert set(_STATUS) == set(ADAPTABLE_KINDS)


class ClientReplay:
    """The recording client's request fields at every recorded call, replayed from the store.

    Each client session (a run's start, each resume: ``RunStore.llm_sessions``; each endpoint
    change) starts from ``RequestShape.for_config`` of the endpoint then in use, and its shape
    changes exactly as the live client's did: ``RequestShape.adapt`` on every recorded refusal,
    ``RequestShape.learn`` on every recorded answer. ``changes`` collects what it changed, which
    matches the run's ``llm_adaptations``.
    """

    def __init__(self, llm: LLMConfig, D: int, sessions: Sequence[int] | None, endpoint_changes: Sequence[dict[str, Any]]) -> None:
        self.llm = llm
        self.D = D
        self.changes_at = sorted(endpoint_changes, key=lambda ch: int(ch.get("llm_calls", 0)))
        self.starts = {0, *(int(n) for n in sessions or ()), *(int(ch.get("llm_calls", 0)) for ch in self.changes_at)}
        self.n = 0
        self.shape: RequestShape | None = None
        self.changes: list[str] = []
        self._built = -1  # the call whose body ``fields`` built last
        self._fresh_at = -1  # the call the current shape was made fresh for

    def config_at(self, n: int) -> LLMConfig:
        """The LLM settings in force for call ``n`` (0-based): the run's, or before a later
        endpoint change, the ones it changed from."""
        llm = self.llm
        for ch in reversed(self.changes_at):
            if n < int(ch.get("llm_calls", 0)):
                was = {k: v for k, v in (ch.get("from") or {}).items() if k in ("base_url", "model", "api_key_env")}
                llm = replace(llm, **was)
        return llm

    def _shape(self) -> RequestShape:
        """The shape of call ``n``: a fresh one where a client session began there, else the one so far."""
        if self.shape is None or (self.n in self.starts and self._fresh_at != self.n):
            self.shape = RequestShape.for_config(self.config_at(self.n))
            self._fresh_at = self.n
        return self.shape

    def fields(self, req: FormRequest) -> dict[str, Any]:
        """The fields (all but the payload) the client sends for ``req`` at the next recorded call;
        ``seed`` is present when it is sent, with a placeholder value (the audit checks the value itself)."""
        body = self._shape().body(req, seed=0)
        self._built = self.n
        return {k: v for k, v in body.items() if k not in req.payload}

    def observe(self, row: dict[str, Any], req: FormRequest) -> None:
        """Feed the recorded outcome of that call (made for ``req``) to the shape, as ``EndpointClient.send`` did."""
        if self._built != self.n:  # the call's body was not built (an unreadable request): build it, as the client did
            self.fields(req)
        shape = self._shape()
        self.n += 1
        if row.get("ok"):
            finish, tokens = response_facts(row.get("response"))
            notes = shape.learn(req, row.get("content"), row.get("reasoning"), finish_reason=finish, reasoning_tokens=tokens,
                                latency_s=row.get("latency_s"), completion_tokens=row.get("completion_tokens"))
            if notes:
                self.changes.append("; ".join(notes))
        elif row.get("error_kind") in _STATUS:
            change, _ = shape.adapt(server_error(_STATUS[row["error_kind"]], row.get("response")))
            if change is not None:
                self.changes.append(change)


def differing_spans(expected: str, recorded: str) -> list[tuple[int, int]]:
    """Spans of ``recorded`` that ``expected`` does not have, widened to whole number tokens.

    The head and the tail the two texts share are equal where they stand; only what lies between
    them is compared character by character (``difflib``, whose time grows with the product of the
    lengths it compares: a prompt of 70,000 characters took a minute whole)."""
    if expected == recorded:
        return []
    head = len(os.path.commonprefix([expected, recorded]))
    most = min(len(expected), len(recorded)) - head
    tail = len(os.path.commonprefix([expected[::-1][:most], recorded[::-1][:most]]))
    sm = difflib.SequenceMatcher(None, expected[head:len(expected) - tail], recorded[head:len(recorded) - tail], autojunk=False)
    spans: list[tuple[int, int]] = []
    for tag, _, _, j1, j2 in sm.get_opcodes():
        if tag == "equal":
            continue
        j1, j2 = j1 + head, j2 + head
        if j1 == j2:  # something the templates write is missing: report where
            j1, j2 = max(0, j1 - 1), min(len(recorded), j1 + 1)
        while j1 > 0 and (recorded[j1 - 1].isalnum() or recorded[j1 - 1] in ".-+_"):
            j1 -= 1
        while j2 < len(recorded) and (recorded[j2].isalnum() or recorded[j2] in ".-+_"):
            j2 += 1
        if spans and j1 <= spans[-1][1]:
            spans[-1] = (spans[-1][0], max(spans[-1][1], j2))
        else:
            spans.append((j1, j2))
    return spans
