"""Bad input: one clear line on stderr, exit code 2, nothing overwritten."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ppprops.cli import main


def _call(capsys, args: list[str]) -> tuple[int, str]:  # type: ignore[no-untyped-def]
    try:
        code = main(args)
    except SystemExit as e:  # argparse
        code = int(e.code or 0)
    err = capsys.readouterr().err
    return code, err


RUN = ["run", "--env", "CartPole", "--quiet"]


@pytest.mark.parametrize(
    "args,needle",
    [
        (["run", "--env", "CartPol", "--quiet"], "did you mean CartPole"),
        (["run", "--env", "NoSuchEnv-v9", "--quiet"], "unknown task 'NoSuchEnv-v9'"),
        (RUN + ["--top-k", "-1"], "--top-k must be >= 0"),
        (RUN + ["--episodes", "0"], "--episodes must be >= 1"),
        (RUN + ["--warmup", "0"], "--warmup must be >= 1"),
        (RUN + ["--iterations", "-3"], "--iterations must be >= 0"),
        (RUN + ["--box", "6,-6"], "--box must be two finite numbers LOW < HIGH"),
        (RUN + ["--box", "a,b"], "expected LOW,HIGH"),
        (RUN + ["--method", "secret"], "invalid choice"),
        (RUN + ["--temperature", "9"], "--temperature must be in [0, 2]"),
        (RUN + ["--base-url", "localhost:8000"], "must start with http"),
        (RUN + ["--base-url", "http://127.0.0.1:9/v1"], "--model is required"),
        (RUN + ["--encode-params", "maybe"], "expected on or off"),
        (["show", "/nonexistent/run"], "is not a ppprops run directory"),
        (["resume", "/nonexistent/run"], "is not a directory"),
        (["policy", "eval", "/nonexistent/p.json"], "does not exist"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, args: list[str], needle: str) -> None:  # type: ignore[no-untyped-def]
    code, err = _call(capsys, args)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ppprops: error:"), err
    assert needle in lines[0]


def test_missing_api_key_variable(capsys, tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.delenv("PPPROPS_TEST_KEY", raising=False)
    code, err = _call(capsys, RUN + ["--warmup", "1", "--iterations", "1", "--final-episodes", "0", "--out", str(tmp_path / "r"),
                                     "--base-url", "http://127.0.0.1:9/v1", "--model", "m", "--api-key-env", "PPPROPS_TEST_KEY"])
    assert code == 2 and "PPPROPS_TEST_KEY" in err and err.count("\n") == 1


def test_output_directory_holding_a_run_is_not_overwritten(capsys, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "r"
    args = RUN + ["--warmup", "2", "--iterations", "0", "--final-episodes", "0", "--out", str(out)]
    assert _call(capsys, args)[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    code, err = _call(capsys, args)
    assert code == 2 and "already holds another run" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize("damage", ["delete", "corrupt", "other_run"])
def test_resume_refuses_a_bad_key_file(capsys, tmp_path: Path, damage: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "r"
    assert _call(capsys, RUN + ["--warmup", "2", "--iterations", "0", "--final-episodes", "0", "--out", str(out)])[0] == 0
    key = out / "secrets.key"
    db_before = (out / "run.sqlite").read_bytes()
    if damage == "delete":
        key.unlink()
    elif damage == "corrupt":
        key.write_text("{not json")
    else:
        doc = json.loads(key.read_text())
        doc["run_id"] = "someone-else"
        key.write_text(json.dumps(doc))
    code, err = _call(capsys, ["resume", str(out), "--quiet"])
    assert code == 2 and "key file" in err and err.count("\n") == 1
    assert (out / "run.sqlite").read_bytes() == db_before


def test_corrupt_store_and_policy_file(capsys, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "run.sqlite").write_bytes(b"this is not sqlite" * 100)
    code, err = _call(capsys, ["show", str(bad)])
    assert code == 2 and "not a readable SQLite database" in err
    pol = tmp_path / "p.json"
    pol.write_text(json.dumps({"format": "ppprops.linear_policy/1", "task": "CartPole", "n_s": 4, "n_a": 2, "W": [[1, 2]], "b": [0, 0]}))
    code, err = _call(capsys, ["policy", "eval", str(pol)])
    assert code == 2 and "W must be 4x2" in err


def test_console_script_exit_code() -> None:
    proc = subprocess.run([sys.executable, "-m", "ppprops", "run", "--env", "Nope"], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.startswith("ppprops: error: unknown task")
