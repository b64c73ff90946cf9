"""The names of the built-in prompt forms (``wire.forms``), for modules that name a form without
building one (``ppprops.methods``: the ``--prompt-form`` values each method takes)."""

from __future__ import annotations

CHAT_FORM = "chat"  # the paper's instruction prompt (wire.forms.CHAT)
DOCUMENT_FORM = "document"  # the history as a document to continue (wire.forms.DOCUMENT)
CRITIC_FORM = "r2po-critic"  # R2PO's critic prompt (wire.forms.CRITIC)
# The forms a user may choose with --prompt-form (``auto`` resolves to one of them).
CHOOSABLE: tuple[str, ...] = (CHAT_FORM, DOCUMENT_FORM)
