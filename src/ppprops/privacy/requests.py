"""The recorded outgoing requests of a run, read back as the provider received them."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import StoreError
from ..store import open_store
from ..wire.forms import CHAT, ENDPOINT_COMPLETIONS, FORMS
from ..wire.transcript import ShownEntry, history_entries


@dataclass(frozen=True)
class Request:
    """One recorded request body: the text of the messages the client wrote, and the sampling seed."""

    call_id: int
    iteration: int
    attempt: int
    text: str  # every non-assistant message, joined (assistant messages are the provider's own words); or the document
    seed: int | None
    entries: tuple[ShownEntry, ...]
    form: str = CHAT.name  # the prompt form the call was recorded under (``wire.forms.FORMS``)
    answer: str | None = None  # the provider's own answer to it (it knows what it said)
    body: str = ""  # the request body as sent

    @property
    def where(self) -> str:
        """Where it is in the run, for findings: ``call <id> (iteration <i>, attempt <k>)``."""
        return f"call {self.call_id} (iteration {self.iteration}, attempt {self.attempt})"


def message_text(content: object) -> str:
    """A message's text: a string, or the text of every part of a list of parts, joined."""
    if isinstance(content, str):
        return content
    if isinstance(content, list):
        return "\n\n".join(str(p.get("text", "")) if isinstance(p, dict) else str(p) for p in content)
    return "" if content is None else str(content)


def parse_request(call_id: int, iteration: int, attempt: int, body: str, answer: str | None = None, form: str | None = None) -> Request:
    """One recorded request of prompt form ``form`` (as the call was recorded): its prompt text (a
    chat body's messages but the provider's own, or a completions body's document), its sampling
    seed and the entries the form prints in it. A body that is not JSON is read as text, with the
    entries of every form; an unknown form reads the entries of every form too."""
    known = FORMS.get(form or CHAT.name)
    try:
        doc = json.loads(body)
        if known is not None and known.endpoint == ENDPOINT_COMPLETIONS:
            text = str(doc.get("prompt", ""))
        else:
            messages = doc.get("messages", [])
            text = "\n\n".join(message_text(m.get("content")) for m in messages if m.get("role") != "assistant")
        seed = doc.get("seed")
    except (json.JSONDecodeError, AttributeError, TypeError):
        text, seed, known = body, None, None  # not JSON: audit the bytes as text, reading entries of any form
    entries = known.entries(text) if known is not None else history_entries(text)
    return Request(call_id, iteration, attempt, text, int(seed) if isinstance(seed, int) else None, tuple(entries),
                   form or CHAT.name, answer, body)


def load_requests(run_dir: Path) -> list[Request]:
    """Every recorded request of a run, in the order sent."""
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    with open_store(run_dir) as store:
        calls = store.llm_calls()
    return [parse_request(int(c["id"]), int(c["iteration"]), int(c["attempt"]), str(c["request"]), c.get("content"), c.get("form"))
            for c in calls]
