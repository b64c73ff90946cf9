"""The embedded server's threads follow the cores busy now, not a lagging load average."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from ppprops.llm import embedded
from ppprops.llm.embedded import busy_cores, default_threads


def test_busy_cores_reads_the_non_idle_share_between_two_samples(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    stat = tmp_path / "stat"
    lines = iter(["cpu  100 0 100 700 100 0 0 0 0 0\n", "cpu  150 0 150 800 100 0 0 0 0 0\n"])

    def fake_sleep(_: float) -> None:
        stat.write_text(next(lines))

    stat.write_text(next(lines))
    monkeypatch.setattr(embedded.time, "sleep", fake_sleep)
    # between the samples: 100 busy of 200 jiffies, so half of every core is busy
    assert busy_cores(stat=str(stat)) == pytest.approx(0.5 * (os.cpu_count() or 1))
    assert busy_cores(stat=str(tmp_path / "missing")) is None


def test_threads_come_from_the_cores_busy_now_before_the_load_average(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(embedded, "busy_cores", lambda: 0.2)  # an editor: the load average may still say 0.8
    monkeypatch.setattr(embedded.os, "getloadavg", lambda: (0.82, 0.5, 0.3))
    assert default_threads(2) == 2
    monkeypatch.setattr(embedded, "busy_cores", lambda: 1.1)  # one busy process: two threads decode slower than one
    assert default_threads(2) == 1
    monkeypatch.setattr(embedded, "busy_cores", lambda: None)  # no /proc/stat: the load average
    assert default_threads(2) == 1
