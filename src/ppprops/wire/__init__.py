"""The provider's side of the trust boundary: everything that may reach the LLM.

Rules, checked by ``tests/unit/test_trust_boundary.py``:
- no module here imports ``ppprops.client``, ``ppprops.evaluation``, ``ppprops.store`` or any
  other client-side module; it depends only on the standard library and itself;
- prompts are built only from ``EncodedEntry`` and ``PromptContext`` values, which the client's
  codec produces after encoding. A raw ``Candidate`` is rejected at run time as well.

The names below load with their module on first use, so that importing one module of the package
(the codec needs ``wire.encoded`` alone) does not load the prompt builders and parsers.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .document import build_document, continuation_grammar, document_target
    from .encoded import EncodedEntry, PromptContext
    from .history import top_k
    from .parse import ParseResult, parse_answer, read_continuation
    from .prompt import build_correction, build_prompt
    from .turns import correction_messages, judge_answer, judge_continuation, prompt_messages

_MODULES = {"build_document": "document", "continuation_grammar": "document", "document_target": "document",
            "EncodedEntry": "encoded", "PromptContext": "encoded", "top_k": "history", "ParseResult": "parse",
            "parse_answer": "parse", "read_continuation": "parse", "build_correction": "prompt", "build_prompt": "prompt",
            "correction_messages": "turns", "judge_answer": "turns", "judge_continuation": "turns", "prompt_messages": "turns"}  # fmt: skip

__all__ = ["EncodedEntry", "ParseResult", "PromptContext", "build_correction", "build_document", "build_prompt",
           "continuation_grammar", "correction_messages", "document_target", "judge_answer", "judge_continuation",
           "parse_answer", "prompt_messages", "read_continuation", "top_k"]


def __getattr__(name: str) -> Any:
    if name in _MODULES:
        from importlib import import_module

        return getattr(import_module(f".{_MODULES[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
