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
from ppprops.testing.fault_server import FaultConfig, FaultServer

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


STUDY = ["study", "create", "--env", "CartPole", "--method", "pp", "--model", "m", "--warmup", "2", "--iterations", "1"]


def test_a_study_on_a_closed_port_is_refused_at_create_and_the_corrected_one_is_made(capsys: pytest.CaptureFixture[str],
                                                                                     tmp_path: Path) -> None:  # fmt: skip
    out = tmp_path / "study"
    url = f"http://127.0.0.1:{_free_port()}/v1"
    assert main([*STUDY, "--base-url", url, "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == (f"ppprops: error: cannot reach the LLM endpoint {url} (--base-url): nothing accepts "
                                                   "connections there (is the server running, on that host and port?)\n")  # fmt: skip
    assert list(tmp_path.iterdir()) == []  # found before the warm-up's trials were handed out, not after them
    with FaultServer() as server:
        assert main([*STUDY, "--base-url", server.base_url, "--out", str(out)]) == 0
        assert server.stats()["requests"] == 0  # the probe is no LLM request
    assert capsys.readouterr().out == f"study directory: {out}\n"
    with open_store(out) as store:
        assert store.status() == "open" and store.llm_calls() == []


def test_create_study_in_python_probes_the_endpoint_first(tmp_path: Path) -> None:
    import ppprops
    from ppprops.errors import ConfigError

    url = f"http://127.0.0.1:{_free_port()}/v1"
    with pytest.raises(ConfigError, match=r"^cannot reach the LLM endpoint http://127\.0\.0\.1:\d+/v1 \(--base-url\)"):
        ppprops.create_study("CartPole", storage=tmp_path / "s", method="pp", warmup=2, iterations=1,
                             llm={"base_url": url, "model": "m"})  # fmt: skip
    assert list(tmp_path.iterdir()) == []


def test_a_new_endpoint_on_resume_is_probed_before_it_is_stored(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out = tmp_path / "r"
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("http_500",))) as server:  # every LLM request fails: kept after the warm-up
        code = main([*RUN, "--base-url", server.base_url, "--retries", "0", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.endswith(f"; the run is saved: continue with 'ppprops resume {out}'\n"), err
    db_before = (out / "run.sqlite").read_bytes()
    url = f"http://127.0.0.1:{_free_port()}/v1"
    assert main(["resume", str(out), "--base-url", url, "--quiet"]) == 2
    assert capsys.readouterr().err.startswith(f"ppprops: error: cannot reach the LLM endpoint {url} (--base-url)")
    assert (out / "run.sqlite").read_bytes() == db_before  # the endpoint it could not reach is not stored


def test_resume_with_an_endpoint_on_a_study_without_env_changes_nothing(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    robot = Path(__file__).resolve().parents[1] / "examples" / "robot_outside" / "robot.toml"
    out = tmp_path / "study"
    with FaultServer() as server:
        assert main(["study", "create", "--task-file", str(robot), "--method", "pp", "--model", "m", "--base-url", server.base_url,
                     "--out", str(out)]) == 0  # fmt: skip
    capsys.readouterr()
    db_before = (out / "run.sqlite").read_bytes()
    assert main(["resume", str(out), "--base-url", "http://127.0.0.1:9/v1"]) == 2
    assert capsys.readouterr().err == (f"ppprops: error: {out} is a study of a task without env, which 'ppprops resume' cannot run: "
                                       f"its next trials come from 'ppprops ask {out}'\n")  # fmt: skip
    assert (out / "run.sqlite").read_bytes() == db_before


def test_an_ask_whose_endpoint_went_down_names_the_study_and_the_ask_to_repeat(capsys: pytest.CaptureFixture[str],
                                                                               tmp_path: Path) -> None:  # fmt: skip
    out = tmp_path / "study"
    with FaultServer() as server:
        assert main([*STUDY[:-4], "--warmup", "1", "--iterations", "2", "--retries", "0", "--base-url", server.base_url,
                     "--out", str(out)]) == 0  # fmt: skip
    # the server is gone: the warm-up trial needs no LLM, the next one does
    assert main(["ask", str(out)]) == 0 and main(["tell", str(out), "0", "--return", "12"]) == 0
    capsys.readouterr()
    assert main(["ask", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ppprops: error: LLM endpoint failed"), err
    assert err.endswith(f"; the study is kept: ask again once the endpoint answers ('ppprops ask {out}')\n")
    with open_store(out) as store:
        assert store.candidate_count() == 1 and store.pending_trials() == []
