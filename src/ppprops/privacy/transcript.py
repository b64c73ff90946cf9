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

    @property
    def where(self) -> str:
        return f"call {self.call_id} (iteration {self.iteration}, attempt {self.attempt})"


def parse_request(call_id: int, iteration: int, attempt: int, body: str) -> Request:
    """A chat body (its ``messages``) or a completions body (its ``prompt``, the document form)."""
    form = None
    try:
        doc = json.loads(body)
        if isinstance(doc.get("prompt"), str) and "messages" not in doc:
            text, form = doc["prompt"], "document"
        else:
            messages = doc.get("messages", [])
            text = "\n\n".join(str(m.get("content", "")) for m in messages if m.get("role") != "assistant")
            form = "chat"
        seed = doc.get("seed")
    except (json.JSONDecodeError, AttributeError, TypeError):
        text, seed = body, None  # not JSON: audit the bytes as text, reading entries of any form
    return Request(call_id, iteration, attempt, text, int(seed) if isinstance(seed, int) else None,
                   tuple(history_entries(text, form)), form or "chat")


def load_requests(run_dir: Path) -> list[Request]:
    """Every recorded request of a run, in the order sent."""
    if not Path(run_dir).is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    store = open_store(run_dir)
    try:
        calls = store.llm_calls()
    finally:
        store.close()
    return [parse_request(int(c["id"]), int(c["iteration"]), int(c["attempt"]), str(c["request"])) for c in calls]
