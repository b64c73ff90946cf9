"""Gemma 3's tokenizer, read from the embedded model's GGUF, for counting tokens without starting the model.

llama.cpp's SPM tokenizer as it runs for Gemma 3 270M (``tokenizer.ggml.model = llama``, no space
prefix): the text is split at the vocabulary's user-defined tokens (runs of newlines and spaces),
each other piece has its spaces written as U+2581 and is merged pair by pair, highest vocabulary
score first (ties: leftmost), and a piece the vocabulary lacks falls back to one token per byte.
No BOS (llama.cpp's ``/tokenize`` adds none). Checked against llama.cpp's own ``/tokenize`` on the
six final Ant-Ultra prompts of benchmark 1 (both forms, K=10 and all; 6,366 to 62,947 tokens): the
same count on every one (benchmarks/RESULTS.md, section 1).
"""

from __future__ import annotations

import heapq
import struct
from functools import cache
from pathlib import Path
from typing import Any, BinaryIO

_FIXED = {0: "<B", 1: "<b", 2: "<H", 3: "<h", 4: "<I", 5: "<i", 6: "<f", 7: "<?", 10: "<Q", 11: "<q", 12: "<d"}
USER_DEFINED = 4  # GGUF token type


def _string(f: BinaryIO) -> str:
    (n,) = struct.unpack("<Q", f.read(8))
    return f.read(n).decode("utf-8", "replace")


def _value(f: BinaryIO, kind: int) -> Any:
    if kind == 8:
        return _string(f)
    if kind == 9:
        item, n = struct.unpack("<IQ", f.read(12))
        if item in _FIXED:
            size = struct.calcsize(_FIXED[item])
            return list(struct.unpack("<" + _FIXED[item][1] * n, f.read(size * n)))
        return [_value(f, item) for _ in range(n)]
    (v,) = struct.unpack(_FIXED[kind], f.read(struct.calcsize(_FIXED[kind])))
    return v


def gguf_metadata(path: Path) -> dict[str, Any]:
    """The key-value metadata of a GGUF file (version 2 or 3); ValueError for another file."""
    with open(path, "rb") as f:
        if f.read(4) != b"GGUF":
            raise ValueError(f"{path} is not a GGUF file")
        f.read(4 + 8)  # version, tensor count
        (count,) = struct.unpack("<Q", f.read(8))
        meta: dict[str, Any] = {}
        for _ in range(count):
            key = _string(f)
            (kind,) = struct.unpack("<I", f.read(4))
            meta[key] = _value(f, kind)
    return meta


class GemmaTokenizer:
    """Counts tokens as llama.cpp tokenizes for the embedded model (module docstring)."""

    def __init__(self, path: Path) -> None:
        meta = gguf_metadata(path)
        if meta.get("tokenizer.ggml.model") != "llama" or meta.get("tokenizer.ggml.add_space_prefix", False):
            raise ValueError(f"{path}: not an SPM vocabulary without a space prefix")
        tokens, self.scores = meta["tokenizer.ggml.tokens"], meta["tokenizer.ggml.scores"]
        self.ids = {t: i for i, t in enumerate(tokens)}
        self.user = sorted((t for t, k in zip(tokens, meta["tokenizer.ggml.token_type"]) if k == USER_DEFINED and t),
                           key=len, reverse=True)

    def _pieces(self, text: str) -> list[tuple[str, bool]]:
        parts = [(text, False)]
        for tok in self.user:
            out: list[tuple[str, bool]] = []
            for s, special in parts:
                if special or tok not in s:
                    out.append((s, special))
                    continue
                chunks = s.split(tok)
                for k, c in enumerate(chunks):
                    if c:
                        out.append((c, False))
                    if k < len(chunks) - 1:
                        out.append((tok, True))
            parts = out
        return parts

    def _spm(self, text: str) -> int:
        sym = list(text.replace(" ", "\u2581"))
        n = len(sym)
        prev, nxt, alive = list(range(-1, n - 1)), [*range(1, n), -1], [True] * n
        heap: list[tuple[float, int, int, str]] = []

        def pair(left: int, right: int) -> None:
            if left >= 0 and right >= 0 and (i := self.ids.get(sym[left] + sym[right])) is not None:
                heapq.heappush(heap, (-self.scores[i], left, right, sym[left] + sym[right]))

        for i in range(n - 1):
            pair(i, i + 1)
        while heap:
            _, left, right, text_ = heapq.heappop(heap)
            if not (alive[left] and alive[right]) or nxt[left] != right or sym[left] + sym[right] != text_:
                continue
            sym[left], alive[right], nxt[left] = text_, False, nxt[right]
            if nxt[right] >= 0:
                prev[nxt[right]] = left
            pair(prev[left], left)
            pair(left, nxt[left])
        return sum(1 if sym[i] in self.ids else len(sym[i].encode("utf-8")) for i in range(n) if alive[i])

    def count(self, text: str) -> int:
        """Tokens of ``text`` (no BOS)."""
        return sum(1 if special else self._spm(s) for s, special in self._pieces(text))


@cache
def gemma_tokenizer() -> GemmaTokenizer:
    """The embedded model's tokenizer, from its GGUF (assembled from the installed package if needed; no server starts)."""
    from ppprops.llm.embedded import model_path

    return GemmaTokenizer(model_path())
