"""An endpoint that is down, or that answers but is no OpenAI-compatible API, is found before the
warm-up: one line, exit 2, no run directory (``llm.probe``), over real HTTP and real sockets. The
probe is no LLM request of the run: the fault server counts none for it, and the store records none."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.store import open_store
from ppprops.testing.fault_server import FaultServer

RUN = ["run", "--env", "CartPole", "--method", "pp", "--model", "m", "--warmup", "2", "--iterations", "1", "--final-episodes", "1",
       "--select-top", "0", "--audit", "off"]  # fmt: skip


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def _web_server(status: int, body: bytes, content_type: str) -> Iterator[str]:
    """A web server that answers every GET with ``status`` and ``body``: not an LLM API."""

    class Page(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/v1"
    finally:
        server.shutdown()
        server.server_close()


def _refused(capsys: pytest.CaptureFixture[str], tmp_path: Path, base_url: str, *extra: str) -> str:
    out = tmp_path / "r"
    code = main([*RUN, "--base-url", base_url, "--out", str(out), *extra])
    captured = capsys.readouterr()
    assert (code, captured.out) == (2, "")
    assert captured.err.count("\n") == 1, captured.err  # no progress bar, no run directory line
    assert not out.exists() and list(tmp_path.iterdir()) == []
    return captured.err.removeprefix("ppprops: error: ").rstrip("\n")


def test_a_closed_port_is_one_line_before_the_warm_up(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    url = f"http://127.0.0.1:{_free_port()}/v1"
    assert _refused(capsys, tmp_path, url) == (f"cannot reach the LLM endpoint {url} (--base-url): nothing accepts connections "
                                               "there (is the server running, on that host and port?)")  # fmt: skip


def test_a_web_page_is_not_an_llm_api(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with _web_server(200, b"<!doctype html><html><body>Welcome to nginx!</body></html>", "text/html; charset=utf-8") as url:
        line = _refused(capsys, tmp_path, url)
    assert line == (f"the LLM endpoint {url} (--base-url) is not an OpenAI-compatible API: GET {url}/models answered text/html "
                    "('<!doctype html><html><body>Welcome to nginx!</body></html>'), not a JSON model list")  # fmt: skip


def test_a_404_on_the_model_list_names_the_api_root(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with _web_server(404, b"Not Found", "text/plain") as url:
        line = _refused(capsys, tmp_path, url)
    assert line == (f"the LLM endpoint {url} (--base-url) is not an OpenAI-compatible API root: GET {url}/models is not found "
                    "(HTTP 404); the root usually ends in /v1, e.g. http://localhost:8000/v1")  # fmt: skip


def test_a_server_that_never_answers_times_out_in_one_line(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with socket.socket() as listening:  # accepts connections (the kernel's backlog) and never answers
        listening.bind(("127.0.0.1", 0))
        listening.listen(8)
        url = f"http://127.0.0.1:{listening.getsockname()[1]}/v1"
        line = _refused(capsys, tmp_path, url, "--timeout", "1")
    assert line == f"the LLM endpoint {url} (--base-url) did not answer GET {url}/models within 1 s (is it overloaded, or not an LLM server?)"


def test_the_probe_is_no_llm_request_of_the_run(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with FaultServer() as server:
        code = main([*RUN, "--base-url", server.base_url, "--out", str(tmp_path / "r"), "--quiet"])
        stats = server.stats()
    assert code == 0, capsys.readouterr().err
    with open_store(tmp_path / "r") as store:
        calls = store.llm_calls()
    assert len(calls) == stats["requests"] == 1  # the one LLM iteration's request; the probe's GET is neither
    assert all("/models" not in c["request"] for c in calls)
