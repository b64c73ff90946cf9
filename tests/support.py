"""Helpers shared by tests (importable because pytest puts tests/ on the path)."""

from __future__ import annotations

import http.server
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager

from ppprops.config import LLMConfig, RunConfig
from ppprops.methods import resolve


def make_config(task: str = "CartPole", method: str = "pp", **kw: object) -> RunConfig:
    llm = kw.pop("llm", LLMConfig())
    # the paper's chat prompt unless a test asks for the document form (tests/test_document_form.py
    # covers that one): these helpers build and read chat messages
    # no selection stage unless a test asks for one (tests/test_study.py covers it): the search alone
    base = dict(warmup=3, iterations=3, top_k=10, episodes=1, final_episodes=3, seed=0, prompt_form="chat", select_top=0)
    base.update(kw)
    return RunConfig(task=task, method=method, mechanisms=resolve(method), llm=llm, **base)  # type: ignore[arg-type]




class _Recorder(http.server.BaseHTTPRequestHandler):
    """Forwards each request to the upstream server and keeps the exact bytes it was sent."""

    upstream = ""
    captured: list[bytes] = []

    def _forward(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        body = self.rfile.read(length) if length else b""
        head = f"{self.command} {self.path} {self.request_version}\r\n" + "".join(f"{k}: {v}\r\n" for k, v in self.headers.items())
        self.captured.append(head.encode() + b"\r\n" + body)
        req = urllib.request.Request(self.upstream + self.path, data=body or None, method=self.command)
        for k, v in self.headers.items():
            if k.lower() not in ("host", "content-length", "connection", "accept-encoding"):
                req.add_header(k, v)
        try:
            with urllib.request.urlopen(req, timeout=600) as resp:
                status, data, ctype = resp.status, resp.read(), resp.headers.get("Content-Type", "application/json")
        except urllib.error.HTTPError as e:
            status, data, ctype = e.code, e.read(), e.headers.get("Content-Type", "application/json")
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    do_GET = do_POST = _forward

    def log_message(self, *args: object) -> None:
        pass


@contextmanager
def recording_proxy(upstream: str) -> Iterator[tuple[str, list[bytes]]]:
    """A loopback HTTP proxy in front of ``upstream``; yields (its URL, the list of raw requests)."""
    captured: list[bytes] = []
    handler = type("Handler", (_Recorder,), {"upstream": upstream.rstrip("/"), "captured": captured})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", captured
    finally:
        server.shutdown()
        server.server_close()


def doc_block(doc: str, first_line: str) -> str:
    """The code block of a doc page that starts with ``first_line`` (a comment naming the file), up
    to its closing fence: the code exactly as the page shows it."""
    start = doc.index(first_line + "\n")
    return doc[start:doc.index("```", start)]


@contextmanager
def offline_llm(spread: float = 0.5) -> Iterator[None]:
    """Within the block, every study given no model talks to an ``EchoOptimizer`` (the offline
    stand-in of ``ppprops.privacy.simulate``) instead of its configured endpoint: the test seam
    for command lines (``ppprops.cli.main``), which take no model object."""
    from unittest import mock

    from ppprops.privacy.simulate import EchoOptimizer

    with mock.patch("ppprops.llm.client.connect", lambda llm, **kw: EchoOptimizer(llm, spread=spread)):
        yield


def chat_request(messages: list[dict[str, str]], D: int, *, iteration: int = 0, attempt: int = 0, temperature: float | None = None):  # type: ignore[no-untyped-def]
    """The chat form's request for ``messages`` asking ``D`` numbers (as the chat form builds its requests)."""
    from ppprops.wire.forms import CHAT, CHAT_TEMPERATURE, FormRequest, answer_budget, params_grammar, params_schema

    return FormRequest(CHAT.name, CHAT.endpoint, D, iteration, attempt, messages=tuple(messages),
                       sampling={"temperature": CHAT_TEMPERATURE if temperature is None else temperature}, answer_tokens=answer_budget(D),
                       explains=True, json_schema=params_schema(D), grammar=params_grammar(D))


def document_request(prompt: str, D: int, *, iteration: int = 0, attempt: int = 0, grammar: str | None = None,
                     temperature: float = 0.6, sampling: dict[str, float] | None = None):  # type: ignore[no-untyped-def]
    """The document form's request for ``prompt`` (a document ending inside its open list) asking ``D`` numbers."""
    from ppprops.wire.forms import DOCUMENT, FormRequest, answer_budget

    return FormRequest(DOCUMENT.name, DOCUMENT.endpoint, D, iteration, attempt, prompt=prompt,
                       sampling={"temperature": temperature, **(sampling or {})}, answer_tokens=answer_budget(D, labels=True),
                       grammar=grammar, stop=("]",))
