"""A Ctrl-C that Python wraps on its way up is still a Ctrl-C.

A SIGINT that lands while a module is imported lazily (the HTTP client loads its resources on first
use) reaches the run as ``RuntimeError: Error calling __set_name__ ...`` caused by the
``KeyboardInterrupt`` (Python 3.11). The run must stop as on any Ctrl-C: status ``interrupted``,
resumable, exit 130 with the one line naming the directory, and no traceback.
"""

from __future__ import annotations

from pathlib import Path
from unittest import mock

import pytest

from ppprops.cli import main
from ppprops.errors import interrupted_by_user
from ppprops.privacy.simulate import EchoOptimizer
from ppprops.runner import resume, start
from ppprops.store import open_store

from support import make_config, offline_llm


def _wrapped() -> RuntimeError:
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise RuntimeError("Error calling __set_name__ on 'cached_property' instance 'with_raw_response' in 'Completions'") from ki
    except RuntimeError as e:
        return e


class DiesWrapped(EchoOptimizer):
    """The offline stand-in, until its third request: then the wrapped Ctrl-C of a lazy import."""

    def send(self, request, *, seed=None):  # type: ignore[no-untyped-def]
        if self.calls == 2:
            raise _wrapped()
        return super().send(request, seed=seed)


def test_an_interrupt_is_found_under_the_errors_python_wraps_it_in() -> None:
    assert interrupted_by_user(KeyboardInterrupt())
    assert interrupted_by_user(_wrapped())
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ValueError("raised while handling it") from None  # suppressed cause, the context remains
    except ValueError as e:
        assert interrupted_by_user(e)
    assert not interrupted_by_user(RuntimeError("Error calling __set_name__ on something that failed by itself"))
    plain = ValueError("no interrupt here")
    plain.__context__ = plain  # a cycle ends the walk
    assert not interrupted_by_user(plain)


def test_a_wrapped_interrupt_marks_the_run_interrupted_and_resume_finishes_it(tmp_path: Path) -> None:
    cfg = make_config("CartPole", "pp", warmup=3, iterations=4, final_episodes=0, seed=3)
    run = tmp_path / "cut"
    with mock.patch("ppprops.llm.client.connect", lambda *a, **kw: DiesWrapped(cfg.llm)), pytest.raises(KeyboardInterrupt):
        start(cfg, run)
    with open_store(run) as store:
        assert store.status() == "interrupted"
        assert len(store.candidates()) == 3 + 2  # the warm-up and the two answered proposals, nothing else
    with offline_llm():
        resume(run)
    with open_store(run) as store:
        assert store.status() == "finished" and [c.index for c in store.candidates()] == list(range(7))


def test_the_command_exits_130_with_the_one_line_on_a_wrapped_interrupt(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    args = ["run", "--env", "CartPole", "--method", "pp", "--warmup", "3", "--iterations", "4", "--final-episodes", "0",
            "--select-top", "0", "--quiet", "--out", str(out)]
    with mock.patch("ppprops.llm.client.connect", lambda llm, **kw: DiesWrapped(llm)):
        assert main(args) == 130
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1] == f"ppprops: interrupted; continue with 'ppprops resume {out}'"
    assert "Traceback" not in err and "RuntimeError" not in err
