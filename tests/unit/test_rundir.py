"""Run directories (``ppprops.rundir``): made atomically, read through one reader, their file names
in one place. A CartPole study is made by hand; nothing is evaluated."""

from __future__ import annotations

from pathlib import Path

import pytest

from ppprops.errors import ConfigError, KeyFileError, StoreError
from ppprops.rundir import DB_NAME, KEY_NAME, POLICY_NAME, check_out, create_run, find_runs, is_run_dir, open_run
from ppprops.settings import build_config
from ppprops.status import RunKind
from ppprops.tasks import get_task


def _config(seed: int = 3):  # type: ignore[no-untyped-def]
    return build_config({"method": "random", "warmup": 2, "iterations": 1, "seed": seed}, task=get_task("CartPole"))


def _run(where: Path) -> Path:
    store, _ = create_run(_config(), where)
    store.close()
    return where


def test_a_run_appears_whole_with_its_store_and_key_and_no_leftover(tmp_path: Path) -> None:
    run = _run(tmp_path / "r")
    assert sorted(p.name for p in run.iterdir()) == sorted([DB_NAME, KEY_NAME])
    assert is_run_dir(run) and not any(p.name.endswith(".creating") for p in tmp_path.iterdir())
    assert (run / KEY_NAME).stat().st_mode & 0o777 == 0o600
    assert (POLICY_NAME, DB_NAME, KEY_NAME) == ("best_policy.json", "run.sqlite", "secrets.key")


def test_the_reader_gives_kind_config_task_secrets_and_policy_path(tmp_path: Path) -> None:
    run = _run(tmp_path / "r")
    with open_run(run, secrets=True) as stored:
        assert stored.kind is RunKind.SEARCH and stored.config.method == "random" and stored.task.D == 10
        assert stored.secrets is not None and len(stored.secrets.a) == 10
        assert stored.policy_path == run / POLICY_NAME and stored.key_path == run / KEY_NAME


def test_a_missing_or_foreign_key_is_refused_or_absent_as_asked(tmp_path: Path) -> None:
    run, other = _run(tmp_path / "r"), _run(tmp_path / "o")
    (run / KEY_NAME).write_bytes((other / KEY_NAME).read_bytes())  # another run's key
    with pytest.raises(KeyFileError):
        open_run(run, secrets=True)
    with open_run(run, secrets="optional") as stored:
        assert stored.secrets is None
    (run / KEY_NAME).unlink()
    with open_run(run) as stored:  # no key read
        assert stored.secrets is None and stored.load_secrets(optional=True) is None


def test_not_a_run_directory_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match=r"is not a ppprops run directory \(no run.sqlite\)"):
        open_run(tmp_path)


def test_an_occupied_output_directory_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    run = _run(tmp_path / "r")
    line = rf"already holds another run; choose a new --out or continue it with 'ppprops resume {run}' \('ppprops ask {run}' for a study driven by ask/tell\)$"
    with pytest.raises(ConfigError, match=line):
        create_run(_config(), run)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    with pytest.raises(ConfigError, match=r"already holds files; choose a new --out$"):
        check_out(tmp_path / "other")
    (tmp_path / "f").write_text("x")
    with pytest.raises(ConfigError, match="is a file, not a directory"):
        check_out(tmp_path / "f")


def test_find_runs_lists_runs_below_a_folder(tmp_path: Path) -> None:
    a, b = _run(tmp_path / "a"), _run(tmp_path / "runs" / "b")
    (tmp_path / ".half.creating").mkdir()
    assert find_runs(tmp_path) == [a, b] and find_runs(tmp_path, recursive=True, with_key=True) == [a, b]
    (b / KEY_NAME).unlink()
    assert find_runs(tmp_path, with_key=True) == [a]
