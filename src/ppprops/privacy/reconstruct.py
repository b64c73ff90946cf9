"""What the client's own code sends, rebuilt from the store, so the audit can account for every byte.

A recorded prompt is compared with the prompt the templates produce from the public context and
the stored *encoded* values of the candidates it shows; whatever differs (text the templates do
not produce) is read number by number. The same is done for R2PO's critic prompt (its rollout
lines taken from the recording, since they are raw by design), for corrections, and for every
top-level field of a request body.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..client.codec import Codec
from ..client.context import prompt_context
from ..client.hardening import codec_for
from ..client.secrets import Secrets
from ..config import RunConfig
from ..llm.client import CHAT_TEMPERATURE, default_max_tokens, params_grammar, params_schema
from ..store import Candidate
from ..tasks.base import Task
from ..wire import EncodedEntry, PromptContext, build_prompt
from ..wire.document import build_document, document_entry
from ..wire.prompt import build_correction, history_entry, template
from ..wire.r2po import Evidence, build_critic_prompt
from ..wire.transcript import ShownEntry, history_entries

CRITIC_HEAD = template("r2po_critic").template.split("$", 1)[0]
_ROLLOUT_LINE = re.compile(r"(\d+): \[([^\]]*)\] -> (.*)")


def client_codec(task: Task, config: RunConfig, secrets: Secrets | None) -> Codec:
    """The run's codec; without the key file, one with neutral secrets (enough for everything but a
    disclosed encoded optimum, which then cannot be verified)."""
    if secrets is None:
        secrets = Secrets(run_id="audit", a=np.ones(task.D), c=1.0)
    return codec_for(secrets, task, config)


def context(task: Task, config: RunConfig, codec: Codec) -> PromptContext:
    return prompt_context(task, config, codec)


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


def prompt_spans(codec: Codec, ctx: PromptContext, text: str, entries: list[ShownEntry],
                 shown: list[Candidate | None]) -> list[tuple[int, int]]:
    """Spans of a recorded ProPS prompt that the templates do not produce from the shown candidates.

    The prose around the entries is compared as a skeleton (each entry one placeholder, so a
    missing or extra entry cannot shift the comparison); each matched entry is compared with the
    entry the proposer builds for its candidate. Unmatched entries are the caller's to report.
    """
    dummy = EncodedEntry(index=-1, params=(0.0,) * ctx.D, ret=0.0)
    expected = build_prompt(ctx, [entry_for(codec, ctx, c) if c is not None else dummy for c in shown])
    exp_skel, _ = _skeleton(expected, history_entries(expected))
    rec_skel, where = _skeleton(text, entries)
    out = [(where[a], where[min(b, len(where) - 1)] if b < len(where) else len(text)) for a, b in differing_spans(exp_skel, rec_skel)]
    for e, c in zip(entries, shown, strict=True):
        if c is None:
            continue
        mine = text[e.start:e.end]
        out += [(e.start + a, e.start + b) for a, b in differing_spans(history_entry(ctx, entry_for(codec, ctx, c)), mine)]
    return sorted(out)


def document_spans(codec: Codec, ctx: PromptContext, text: str, entries: list[ShownEntry],
                   shown: list[Candidate | None]) -> list[tuple[int, int]]:
    """Spans of a recorded document-form prompt (``wire.document.build_document``) that the
    document templates do not produce from the shown candidates: the header and the open block
    as a skeleton (each entry one placeholder), each matched entry against the entry built for its
    candidate. With an unmatched entry the target cannot be rebuilt; it is the caller's to report."""
    dummy = EncodedEntry(index=-1, params=(0.0,) * ctx.D, ret=0.0)
    expected = build_document(ctx, [entry_for(codec, ctx, c) if c is not None else dummy for c in shown] or [dummy])
    exp_skel, _ = _skeleton(expected, history_entries(expected, "document") if shown else [])
    rec_skel, where = _skeleton(text, entries)
    out = [(where[a], where[min(b, len(where) - 1)] if b < len(where) else len(text)) for a, b in differing_spans(exp_skel, rec_skel)]
    for e, c in zip(entries, shown, strict=True):
        if c is None:
            continue
        mine = text[e.start:e.end]
        out += [(e.start + a, e.start + b) for a, b in differing_spans(document_entry(ctx, entry_for(codec, ctx, c)), mine)]
    return sorted(out)


def _skeleton(text: str, entries: list[ShownEntry]) -> tuple[str, list[int]]:
    """The text with each entry replaced by one NUL, and the text offset of each skeleton character."""
    parts, where, pos = [], [], 0
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
    m = re.search(r"\n3\. The candidate:\nparams: (\[[^\]\n]*\])", text)
    return m.group(1) if m else None


def expected_correction(answer: str | None, D: int, errors: list[str]) -> list[str]:
    """Corrections the proposer could have sent after ``answer`` (a parse failure, or a request error)."""
    from ..wire import parse_answer

    out = []
    result = parse_answer(answer or "", D)
    if not result.ok:
        out.append(build_correction(result.detail, D))
    out += [build_correction(e, D) for e in errors if e]
    out.append(build_correction("the request failed", D))
    return out


def expected_fields(config: RunConfig, task: Task) -> dict[str, Any]:
    """Top-level request fields other than messages and seed, as ``ChatClient.body`` sets them.

    ``response_format`` and ``grammar`` are alternatives (structured output); either may be absent.
    """
    from ..llm.embedded import MODEL_ALIAS

    llm = config.llm
    D = task.D
    out: dict[str, Any] = {
        "model": llm.model if llm.base_url else MODEL_ALIAS,
        "temperature": CHAT_TEMPERATURE if llm.temperature is None else llm.temperature,
        "max_tokens": llm.max_tokens or default_max_tokens(D),
        "response_format": {"type": "json_schema",
                            "json_schema": {"name": "policy_parameters", "schema": params_schema(D), "strict": True}},
        "grammar": params_grammar(D),
    }
    if llm.reasoning_effort:
        out["reasoning_effort"] = llm.reasoning_effort
    return out


def differing_spans(expected: str, recorded: str) -> list[tuple[int, int]]:
    """Spans of ``recorded`` that ``expected`` does not have, widened to whole number tokens."""
    if expected == recorded:
        return []
    sm = difflib.SequenceMatcher(None, expected, recorded, autojunk=False)
    spans = []
    for tag, _, _, j1, j2 in sm.get_opcodes():
        if tag == "equal":
            continue
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
