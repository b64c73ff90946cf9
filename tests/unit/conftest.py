"""The fast lane (``python -m pytest tests/unit``): tests of the core pieces that start no model and
no process of ppprops's own, a minute or so on 2 cores. This fixture keeps them so: a test here that
starts a ppprops command line, the embedded model's server or a worker pool fails. (Libraries may
still run their own probes, such as ``uname -p``.)"""

from __future__ import annotations

import concurrent.futures
import subprocess
from collections.abc import Iterator

import pytest


def _refuse(what: str) -> AssertionError:
    return AssertionError(f"a fast-lane test started {what}; move it out of tests/unit")


@pytest.fixture(autouse=True)
def no_process_of_our_own(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    popen = subprocess.Popen.__init__

    def checked(self: subprocess.Popen[bytes], args: object, *rest: object, **kwargs: object) -> None:
        if "ppprops" in str(args):
            raise _refuse(f"a ppprops process ({args!r})")
        popen(self, args, *rest, **kwargs)  # type: ignore[arg-type]

    def pool(*args: object, **kwargs: object) -> None:
        raise _refuse("a process pool")

    monkeypatch.setattr(subprocess.Popen, "__init__", checked)
    monkeypatch.setattr(concurrent.futures.ProcessPoolExecutor, "__init__", pool)
    yield
