"""What a first run says: every check that needs no episode runs before
anything is printed or written, flags are never matched by prefix, and a document-form run says
once that it does not show the components and diagnostics asked for."""

from __future__ import annotations

from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.summary import format_summary, run_summary

from support import offline_llm

TINY = ["--method", "random", "--warmup", "2", "--iterations", "1", "--final-episodes", "0", "--select-top", "0"]


def _run(capsys: pytest.CaptureFixture[str], args: list[str]) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_an_out_that_is_a_file_is_named_as_such_and_nothing_is_announced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "afile").write_text("x")
    code, out, err = _run(capsys, ["run", "--env", "CartPole", *TINY, "--out", str(tmp_path / "afile")])
    assert code == 2 and out == "" and err == f"ppprops: error: --out {tmp_path / 'afile'} is a file, not a directory; choose a new --out\n"


def test_an_occupied_out_is_refused_before_the_run_directory_is_announced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    code, _, err = _run(capsys, ["run", "--env", "CartPole", *TINY, "--out", str(tmp_path / "busy")])
    assert code == 2 and "run directory:" not in err and err.count("\n") == 1
    assert "output directory" in err and "already holds files" in err
    assert sorted(p.name for p in (tmp_path / "busy").iterdir()) == ["notes.txt"]


def test_an_unset_api_key_variable_is_found_before_the_warm_up(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PPPROPS_TEST_UNSET_KEY", raising=False)
    code, _, err = _run(capsys, ["run", "--env", "CartPole", "--method", "pp", "--warmup", "3", "--iterations", "2",
                                 "--base-url", "http://127.0.0.1:9/v1", "--model", "m", "--api-key-env", "PPPROPS_TEST_UNSET_KEY",
                                 "--out", str(tmp_path / "r")])  # fmt: skip
    assert code == 2 and "run directory:" not in err
    assert err == "ppprops: error: --api-key-env names PPPROPS_TEST_UNSET_KEY, but that environment variable is empty or unset\n"
    assert not (tmp_path / "r").exists()  # no half-finished run


@pytest.mark.parametrize("abbreviated", [["--warm", "2"], ["--iter", "1"], ["--final-ep", "0"]])
def test_abbreviated_flags_are_not_taken_as_prefixes(tmp_path: Path, capsys: pytest.CaptureFixture[str], abbreviated: list[str]) -> None:
    with pytest.raises(SystemExit) as exited:  # argparse exits while parsing, with one line
        main(["run", "--env", "CartPole", "--method", "random", *abbreviated, "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and err == f"ppprops: error: unrecognized arguments: {' '.join(abbreviated)}\n"
    assert not (tmp_path / "r").exists()


def test_the_document_form_says_once_that_it_does_not_show_the_feedback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with offline_llm():
        code, _, err = _run(capsys, ["run", "--env", "Acrobot", "--method", "pp", "--warmup", "3", "--iterations", "3", "--final-episodes",
                                     "0", "--select-top", "0", "--out", str(tmp_path / "doc"), "--quiet"])  # fmt: skip
    assert code == 0
    note = ("note: the document form (the embedded model's default) shows the LLM the returns only, not the detailed "
            "feedback of this task (2 diagnostics); --prompt-form chat shows it\n")
    assert err.count("note: ") == 1 and note in err
    assert ("\nnote     the document form showed the LLM the returns only, not the detailed feedback of this task (2 diagnostics); "
            "--prompt-form chat shows it\n") in format_summary(run_summary(tmp_path / "doc"))
    with offline_llm():  # the chat form shows them: nothing to say
        code, _, err = _run(capsys, ["run", "--env", "Acrobot", "--method", "pp", "--prompt-form", "chat", "--warmup", "3", "--iterations",
                                     "1", "--final-episodes", "0", "--select-top", "0", "--out", str(tmp_path / "chat"), "--quiet"])  # fmt: skip
    assert code == 0 and "note: " not in err and run_summary(tmp_path / "chat")["notes"] == []
