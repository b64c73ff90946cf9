"""The provider's side of the trust boundary: everything that may reach the LLM.

Rules, checked by ``tests/test_trust_boundary.py``:
- no module here imports ``ppprops.client``, ``ppprops.evaluation``, ``ppprops.store`` or any
  other client-side module; it depends only on the standard library and itself;
- prompts are built only from ``EncodedEntry`` and ``PromptContext`` values, which the client's
  codec produces after encoding. A raw ``Candidate`` is rejected at run time as well.
"""

from .encoded import EncodedEntry, PromptContext
from .history import top_k
from .parse import ParseResult, parse_answer
from .prompt import build_correction, build_prompt
from .turns import correction_messages, judge_answer, prompt_messages

__all__ = ["EncodedEntry", "ParseResult", "PromptContext", "build_correction", "build_prompt", "correction_messages", "judge_answer",
           "parse_answer", "prompt_messages", "top_k"]
