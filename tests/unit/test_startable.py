"""Nothing on disk before a run can start: a paper task whose simulator extra is missing, or whose
env cannot be made, is one line and exit 2 from ``ppprops run`` and ``ppprops study create`` (and
the same error from ``ppprops.search`` / ``ppprops.create_study``), with no run directory, no
parent folder and no half-made temporary left; a rerun with the same ``--out`` then starts.

A missing extra is simulated by making its import fail (``sys.modules["mujoco"] = None``), which is
what ``tasks.mujoco.require_mujoco``, the paper MuJoCo tasks' setup, meets on a base install.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

import ppprops
from ppprops.cli import main
from ppprops.errors import MissingExtraError
from ppprops.store import open_store
from ppprops.tasks.envs import EnvError

MUJOCO = "each MuJoCo task (Ant-v5, Humanoid-v5) needs the 'mujoco' extra: pip install 'ppprops[mujoco]'"
SHORT = ["--method", "random", "--warmup", "1", "--iterations", "1", "--final-episodes", "1", "--select-top", "0", "--quiet"]


@pytest.fixture
def no_mujoco(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    monkeypatch.setitem(sys.modules, "mujoco", None)  # `import mujoco` raises ImportError, as on a base install
    return monkeypatch


def _nothing_under(root: Path) -> None:
    assert list(root.iterdir()) == [], list(root.iterdir())


def test_run_with_a_missing_extra_leaves_nothing_and_the_same_out_then_starts(tmp_path: Path, no_mujoco: pytest.MonkeyPatch,
                                                                            capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "runs" / "ant"
    assert main(["run", "--env", "Ant-Ultra", "--out", str(out), *SHORT]) == 2
    assert capsys.readouterr() == ("", f"ppprops: error: {MUJOCO}\n")
    _nothing_under(tmp_path)  # no run directory, not even its parent folder
    no_mujoco.undo()  # the user installs the extra
    assert main(["run", "--env", "Ant-Ultra", "--out", str(out), *SHORT, "--audit", "off"]) == 0
    capsys.readouterr()
    with open_store(out) as store:
        assert store.status() == "finished" and store.candidate_count() == 2


def test_study_create_with_a_missing_extra_leaves_nothing(tmp_path: Path, no_mujoco: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "create", "--env", "Ant-Ultra", "--method", "random", "--out", str(tmp_path / "s")]) == 2
    assert capsys.readouterr() == ("", f"ppprops: error: {MUJOCO}\n")
    _nothing_under(tmp_path)


def test_search_and_create_study_with_a_missing_extra_leave_nothing(tmp_path: Path, no_mujoco: pytest.MonkeyPatch) -> None:
    with pytest.raises(MissingExtraError) as raised:
        ppprops.search("Ant-Ultra", method="random", warmup=1, iterations=1, out=tmp_path / "a")
    assert str(raised.value) == MUJOCO
    with pytest.raises(MissingExtraError) as raised:
        ppprops.create_study("Ant-Ultra", method="random", storage=tmp_path / "b")
    assert str(raised.value) == MUJOCO
    _nothing_under(tmp_path)


def test_a_paper_env_that_cannot_be_made_is_found_before_the_run_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    from gymnasium.envs.classic_control.cartpole import CartPoleEnv

    def broken(self: CartPoleEnv, *args: object, **kwargs: object) -> None:
        raise RuntimeError("no display")

    monkeypatch.setattr(CartPoleEnv, "__init__", broken)
    line = f"making CartPole-v1 failed: RuntimeError: no display (at {__file__}:{broken.__code__.co_firstlineno + 1}, in broken)"
    assert main(["run", "--env", "CartPole", "--out", str(tmp_path / "runs" / "c"), *SHORT]) == 2
    assert capsys.readouterr() == ("", f"ppprops: error: {line}\n")
    with pytest.raises(EnvError) as raised:
        ppprops.search("CartPole", method="random", warmup=1, iterations=1, out=tmp_path / "runs" / "d")
    assert str(raised.value) == line
    _nothing_under(tmp_path)
