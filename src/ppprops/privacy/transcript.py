"""The recorded outgoing requests of a run, read back as the provider received them."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import StoreError
from ..store import open_store
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
    form: str = "chat"  # chat (messages) or document (a completions prompt, wire.document)
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


def parse_request(call_id: int, iteration: int, attempt: int, body: str, answer: str | None = None) -> Request:
    """A chat body (its ``messages``) or a completions body (its ``prompt``, the document form)."""
    form = None
    try:
        doc = json.loads(body)
        if isinstance(doc.get("prompt"), str) and "messages" not in doc:
            text, form = doc["prompt"], "document"
        else:
            messages = doc.get("messages", [])
            text = "\n\n".join(message_text(m.get("content")) for m in messages if m.get("role") != "assistant")
            form = "chat"
        seed = doc.get("seed")
    except (json.JSONDecodeError, AttributeError, TypeError):
        text, seed = body, None  # not JSON: audit the bytes as text, reading entries of any form
    return Request(call_id, iteration, attempt, text, int(seed) if isinstance(seed, int) else None,
                   tuple(history_entries(text, form)), form or "chat", answer, body)


def load_requests(run_dir: Path) -> list[Request]:
    """Every recorded request of a run, in the order sent."""
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    with open_store(run_dir) as store:
        calls = store.llm_calls()
    return [parse_request(int(c["id"]), int(c["iteration"]), int(c["attempt"]), str(c["request"]), c.get("content"))
            for c in calls]
