"""The provider's side of the trust boundary: everything that may reach the LLM.

Rules, checked by ``tests/unit/test_trust_boundary.py``:
- no module here imports ``ppprops.client``, ``ppprops.evaluation``, ``ppprops.store`` or any
  other client-side module; it depends only on the standard library and itself;
- prompts are built only from ``EncodedEntry`` and ``PromptContext`` values, which the client's
  codec produces after encoding. A raw ``Candidate`` is rejected at run time as well.
"""

from .document import build_document, continuation_grammar, document_target
from .encoded import EncodedEntry, PromptContext
from .history import top_k
from .parse import ParseResult, parse_answer, read_continuation
from .prompt import build_correction, build_prompt
from .turns import correction_messages, judge_answer, judge_continuation, prompt_messages

__all__ = ["EncodedEntry", "ParseResult", "PromptContext", "build_correction", "build_document", "build_prompt",
           "continuation_grammar", "correction_messages", "document_target", "judge_answer", "judge_continuation",
           "parse_answer", "prompt_messages", "read_continuation", "top_k"]
