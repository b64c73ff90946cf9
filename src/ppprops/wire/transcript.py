"""Reads history entries back out of a prompt, as printed, for the audit and the attacks.

Positional reading: each entry's fields keep the exact strings the prompt printed (so a reader
knows their precision) and their place (which parameter, which component), so a printed value
can be compared with the raw value of the same quantity rather than with every number around.
Standard library only, like the rest of ``ppprops.wire``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

from .prompt import COMPONENTS_PREFIX, DIAGNOSTICS_PREFIX, template

NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_PAIR_SPLIT = re.compile(r", (?=[A-Za-z_][\w.]*=)")


_INDEXED_PARAM = re.compile(r"params\[(\d+)\]: ([^,\n]+)")
# The parameter field of each history-entry template (see wire.prompt.PARAMS_STYLES).
_LIST_RX = r"\[(?P<params>[^\]\n]*)\]"
_PARAMS_RX = {
    "history_entry": _LIST_RX,
    "history_entry_indexed": r"(?P<indexed>params\[\d+\]: [^,\n]+(?:, params\[\d+\]: [^,\n]+)*)",
    "document_entry": _LIST_RX,  # wire.document: return first, then the list
}


def _entry_pattern(name: str) -> re.Pattern[str]:
    """A history-entry template turned into a regex, so template edits cannot silently blind the audit."""
    t = template(name).template
    parts = re.split(r"(\$params|\$ret|\$components|\$diagnostics)", t)
    rx = ""
    for part in parts:
        if part == "$params":
            rx += _PARAMS_RX[name]
        elif part == "$ret":
            rx += r"(?P<ret>\S+)"
        elif part == "$components":
            rx += f"(?:{re.escape(COMPONENTS_PREFIX)}(?P<components>[^\\n]*))?"
        elif part == "$diagnostics":
            rx += f"(?:{re.escape(DIAGNOSTICS_PREFIX)}(?P<diagnostics>[^\\n]*))?"
        else:
            rx += re.escape(part)
    return re.compile(rx)


@dataclass(frozen=True)
class ShownEntry:
    """One history entry as printed: strings, not floats, so their precision is known."""

    start: int
    end: int
    params: tuple[str, ...]
    ret: str
    components: tuple[tuple[str, str], ...] = ()
    diagnostics: tuple[tuple[str, str], ...] = ()


def _pairs(text: str | None) -> tuple[tuple[str, str], ...]:
    if not text:
        return ()
    out = []
    for item in _PAIR_SPLIT.split(text):
        key, sep, value = item.partition("=")
        if sep:
            out.append((key.strip(), value.strip()))
    return tuple(out)


UNREADABLE = "(indices out of order)"


def _indexed_params(text: str) -> tuple[str, ...]:
    """Values of ``params[i]: v`` pairs by index. Indices out of order give an entry whose
    parameters cannot be read, which the audit reports as unverified rather than skipping."""
    pairs = _INDEXED_PARAM.findall(text)
    if [int(i) for i, _ in pairs] != list(range(len(pairs))):
        return (UNREADABLE,)
    return tuple(v.strip() for _, v in pairs)


def _labelled_params(text: str) -> tuple[str, ...]:
    """Values of a labelled list ``0:v,1:v,...`` (the document form; with row labels only some
    values carry one: ``0:v,v,2:v,v``). A first value without a label, or a label that is not its
    value's position, gives an entry whose parameters cannot be read (unverified, never skipped);
    the audit also compares each entry with the form's own rendering, which fixes where labels go."""
    items = [v.strip() for v in text.split(",") if v.strip()]
    out = []
    for i, item in enumerate(items):
        label, sep, value = item.partition(":")
        if (not sep and i == 0) or (sep and label.strip() != str(i)):
            return (UNREADABLE,)
        out.append(value.strip() if sep else item)
    return tuple(out)


def history_entries(text: str, templates: Sequence[str] | None = None) -> list[ShownEntry]:
    """Every history entry in a prompt, in the order printed: of the entry ``templates`` (a prompt
    form's, ``wire.forms.PromptForm.entry_templates``), or of every known template when None."""
    out: list[ShownEntry] = []
    names = tuple(templates) if templates is not None else tuple(_PARAMS_RX)
    for name in names:
        for m in _entry_pattern(name).finditer(text):
            groups = m.groupdict()
            if groups.get("params") is not None and name == "document_entry":
                params = _labelled_params(groups["params"])
            elif groups.get("params") is not None:
                params = tuple(v.strip() for v in groups["params"].split(",") if v.strip())
            else:
                params = _indexed_params(groups["indexed"])
            out.append(ShownEntry(m.start(), m.end(), params, m.group("ret"), _pairs(groups.get("components")),
                                  _pairs(groups.get("diagnostics"))))
    out.sort(key=lambda e: e.start)
    return out


def open_target(text: str) -> tuple[int, str] | None:
    """The document form's open block: (offset, printed target return) of the ``return:`` line
    that the prompt ends after (inside its ``params: [``), else None."""
    t = template("document_entry").template
    before, rest = t.split("$ret", 1)
    between = rest.split("$params", 1)[0]
    m = re.search(re.escape(before) + r"(?P<ret>\S+)" + re.escape(between) + r"\[\Z", text)
    return (m.start("ret"), m.group("ret")) if m else None


def outside_entries(text: str, entries: list[ShownEntry]) -> list[tuple[int, str]]:
    """The stretches of text that are not history entries (the prose), with their offsets."""
    out: list[tuple[int, str]] = []
    pos = 0
    for e in entries:
        if e.start > pos:
            out.append((pos, text[pos:e.start]))
        pos = e.end
    if pos < len(text):
        out.append((pos, text[pos:]))
    return out


def number_tokens(text: str) -> list[tuple[int, str]]:
    """Numbers as printed in free text (offset, token); digits inside words (s[0], v1) are skipped."""
    return [(m.start(), m.group(0)) for m in re.finditer(rf"(?<![\w.]){NUMBER}(?![\w])", text)]
