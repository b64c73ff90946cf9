"""The smaller front-door lines, each as a user meets it: a text given as a return on stdin, a tell
after the study is finalized or spent, a binary task file or key file, the episode seeds in
``show --json``, and the help of ``show`` and ``audit`` (which take a study directory too)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.store import open_store

ROBOT = Path(__file__).resolve().parents[2] / "examples" / "robot_outside" / "robot.toml"
FEEDBACK = ["--component", "reward_distance=-9", "--component", "reward_effort=-1"]


@pytest.fixture
def study(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Path:
    """A study of the rig arm (no env; random search: no LLM): 1 warm-up trial and 1 search trial."""
    out = tmp_path / "study"
    assert main(["study", "create", "--task-file", str(ROBOT), "--method", "random", "--warmup", "1", "--iterations", "1",
                 "--seed", "4", "--out", str(out)]) == 0  # fmt: skip
    assert main(["ask", str(out)]) == 0
    capsys.readouterr()
    return out


def _tell_stdin(study: Path, text: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    monkeypatch.setattr("sys.stdin", io.StringIO(text))
    code = main(["tell", str(study), "0", "--stdin"])
    return code, capsys.readouterr().err


@pytest.mark.parametrize(("given", "line"), [
    ('{"return": "fast"}', "episode return 'fast' is not a finite number"),
    ('{"returns": ["fast"]}', "episode return 'fast' is not a finite number"),
    ('{"return": [1, 2]}', 'stdin: "return" is one episode\'s return; give several as "returns": [...]'),
    ('{"returns": 5}', 'stdin: "returns" must be a list, one return per episode, got 5'),
])  # fmt: skip
def test_tell_stdin_says_what_is_wrong_with_the_return(study: Path, given: str, line: str, monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert _tell_stdin(study, given, monkeypatch, capsys) == (2, f"ppprops: error: {line}\n")
    with open_store(study) as store:
        assert store.candidate_count() == 0 and store.pending_trial() is not None  # nothing stored


def test_tell_stdin_takes_one_episode_as_return(study: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO('{"return": -10, "components": {"reward_distance": -9, "reward_effort": -1}}'))
    assert main(["tell", str(study), "0", "--stdin"]) == 0
    assert capsys.readouterr().out == "trial 0: return -10; best -10 (trial 0); 1 of 2 told\n"


def test_a_tell_when_nothing_is_left_says_to_finalize_and_after_finalize_that_it_is_final(study: Path,
                                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tell", str(study), "0", "--return", "-10", *FEEDBACK]) == 0
    assert main(["ask", str(study)]) == 0
    assert main(["tell", str(study), "1", "--return", "-8", *FEEDBACK]) == 0
    capsys.readouterr()
    assert main(["tell", str(study), "2", "--return", "-7", *FEEDBACK]) == 2
    assert capsys.readouterr().err == (f"ppprops: error: no trial is pending and study {study} has nothing more to ask (2 of 2 trials "
                                       "told): finalize it\n")
    assert main(["study", "finalize", str(study)]) == 0
    capsys.readouterr()
    assert main(["tell", str(study), "2", "--return", "-7", *FEEDBACK]) == 2
    assert capsys.readouterr().err == f"ppprops: error: study {study} is finalized (2 of 2 trials told): nothing more can be told\n"
    assert main(["tell", str(study), "1", "--return", "-7", *FEEDBACK]) == 2
    assert capsys.readouterr().err == "ppprops: error: trial 1 was already told; each trial is told once\n"


def test_a_binary_task_file_or_config_file_is_not_text(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    binary = tmp_path / "robot.toml"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    assert main(["run", "--task-file", str(binary), "--out", str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err == f"ppprops: error: task file {binary} cannot be read: it is not text (byte 0x89 at offset 0 is not UTF-8)\n"
    assert main(["run", "--config", str(binary), "--out", str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err == f"ppprops: error: config file {binary} cannot be read: it is not text (byte 0x89 at offset 0 is not UTF-8)\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.toml"]


def test_a_garbage_key_file_is_corrupt_and_says_why(study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key = study / "secrets.key"
    key.write_bytes(b'{"format": \xff\xfe garbage')
    assert main(["tell", str(study), "0", "--return", "-10", *FEEDBACK]) == 2
    assert capsys.readouterr().err == f"ppprops: error: key file {key} is corrupt: it is not text (byte 0xff at offset 11 is not UTF-8)\n"


def test_show_json_gives_each_candidates_episode_seeds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "r"
    assert main(["run", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "1", "--episodes", "2",
                 "--select-top", "1", "--select-episodes", "3", "--final-episodes", "1", "--out", str(out), "--quiet",
                 "--audit", "off"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["show", str(out), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)["candidates"]
    with open_store(out) as store:
        stored = store.candidates()
    assert [c["seeds"] for c in shown] == [list(c.seeds) for c in stored]
    assert [len(c["seeds"]) for c in shown] == [2, 2, 2, 3]  # the selection stage's re-evaluation ran 3 episodes
    assert [c["episode_returns"] for c in shown] == [list(c.feedback.episode_returns) for c in stored]


@pytest.mark.parametrize("command", ["show", "audit"])
def test_show_and_audit_say_they_take_a_study_directory(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main([command, "--help"])
    out = capsys.readouterr().out
    assert exited.value.code == 0 and "  dir " in out
    assert [line.split(None, 1)[1] for line in out.splitlines() if line.startswith("  dir ")] == ["a run or study directory"]


def test_a_new_study_audits_clean_with_nothing_sent_and_resume_of_a_rig_study_leaves_no_lock(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "new"
    assert main(["study", "create", "--task-file", str(ROBOT), "--method", "pp-hardened", "--seed", "4", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["audit", str(out), "--json"]) == 0  # no candidate yet: an (N, D) of N = 0, not a traceback
    doc = json.loads(capsys.readouterr().out)
    assert (doc["requests"], doc["entries"], doc["findings"]) == (0, 0, [])
    assert doc["verdict"].startswith("CLEAN") and doc["notes"] == []
    key = out / "secrets.key"
    text = key.read_bytes()
    for state, damage in (("unusable (damaged, or another run's)", lambda: key.write_bytes(b"\xa0 garbage")), ("missing", key.unlink)):
        damage()
        assert main(["audit", str(out), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["notes"] == [
            f"the key file {key} is {state}: what was sent is checked without the secrets, so the requests' sampling seeds "
            "are not verified, and the attacks are scored from the stored values where the run's maps allow it"]
    key.write_bytes(text)
    before = sorted(p.name for p in out.iterdir())
    assert main(["resume", str(out)]) == 2
    assert capsys.readouterr().err == ("ppprops: error: task RigArm has no env: drive it with ask/tell "
                                       "('ppprops ask' / 'ppprops tell')\n")
    assert sorted(p.name for p in out.iterdir()) == before  # no lock file made for a loop that cannot run


def test_policy_eval_of_a_rig_policy_is_one_line_with_no_progress_bar(study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tell", str(study), "0", "--return", "-10", *FEEDBACK]) == 0
    assert main(["ask", str(study)]) == 0
    assert main(["tell", str(study), "1", "--return", "-8", *FEEDBACK]) == 0
    assert main(["study", "finalize", str(study)]) == 0
    capsys.readouterr()
    assert main(["policy", "eval", str(study)]) == 2  # progress on: the bar would come first
    assert capsys.readouterr().err == ("ppprops: error: task RigArm has no env: it describes a robot outside Python, whose "
                                       "episodes only its own driver runs; search it with ask/tell (`ppprops ask` / `ppprops "
                                       "tell`, or Study.ask / Study.tell), and evaluate its policy on the robot\n")
