"""Bad input: one clear line on stderr, exit code 2, nothing overwritten."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main


def _call(capsys, args: list[str]) -> tuple[int, str]:  # type: ignore[no-untyped-def]
    try:
        code = main(args)
    except SystemExit as e:  # argparse
        code = int(e.code or 0)
    err = capsys.readouterr().err
    return code, err


RUN = ["run", "--env", "CartPole", "--quiet", "--select-top", "0"]


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
        (RUN + ["--method", "vanilla", "--number-format", "grid"],
         "--number-format grid needs encoded parameters; --method vanilla sends them raw (use decimal or auto)"),
        (RUN + ["--encode-params", "off", "--number-format", "grid"],  # pp encodes: the override is what sends them raw
         "--number-format grid needs encoded parameters; --encode-params off sends them raw (use decimal or auto)"),
        (RUN + ["--number-format", "hex"], "invalid choice: 'hex'"),
        (RUN + ["--box", "a,b"], "expected LOW,HIGH"),
        (RUN + ["--method", "secret"], "invalid choice"),
        (RUN + ["--temperature", "9"], "--temperature must be in [0, 2]"),
        (RUN + ["--base-url", "localhost:8000"], "must start with http"),
        (RUN + ["--base-url", "http://127.0.0.1:99999/v1", "--model", "m"], "--base-url has a port outside 1-65535: 'http://127.0.0.1:99999/v1'"),
        (RUN + ["--base-url", "http://127.0.0.1:0/v1", "--model", "m"], "--base-url has a port outside 1-65535"),
        (RUN + ["--base-url", "http:///v1", "--model", "m"], "--base-url names no host: 'http:///v1'"),
        (RUN + ["--base-url", "http://127.0.0.1:9/v1"], "--model is required"),
        (RUN + ["--encode-params", "maybe"], "expected on or off"),
        (["show", "/nonexistent/run"], "is not a ppprops run directory"),
        (["resume", "/nonexistent/run"], "is not a directory"),
        (["policy", "eval", "/nonexistent/p.json"], "does not exist"),
        (RUN + ["--warmup", "10001"], "--warmup must be <= 10000"),
        (RUN + ["--iterations", "100001"], "--iterations must be <= 100000"),
        (RUN + ["--episodes", "10001"], "--episodes must be <= 10000"),
        (RUN + ["--parse-retries", "11"], "--parse-retries must be <= 10"),
        (RUN + ["--retries", "-1"], "--retries must be in [0, 20]"),
        (RUN + ["--retry-base-delay", "nan"], "--retry-base-delay must be in [0, 3600] seconds"),
        (RUN + ["--retry-base-delay", "5", "--retry-max-delay", "1"], "--retry-max-delay (1.0) must be >= --retry-base-delay"),
        (RUN + ["--on-llm-failure", "retry"], "invalid choice"),
        (["run", "--quiet"], "--env or --task-file is required"),
        # a model name for the embedded model, which would answer instead and be recorded as that model
        (RUN + ["--model", "gpt-4"], "--model gpt-4 names a model at --base-url, and no --base-url was given"),
        # LLM and prompt settings for a method that sends no prompt, refused like its mechanism switches
        (RUN + ["--method", "random", "--prompt-form", "chat"], "--prompt-form does not apply to --method random: it sends no prompt"),
        (RUN + ["--method", "cmaes", "--base-url", "http://127.0.0.1:9/v1", "--model", "m"],
         "--base-url, --model do not apply to --method cmaes: it sends no prompt"),
        (RUN + ["--method", "random", "--top-k", "3"], "--top-k does not apply to --method random"),
        (RUN + ["--config", "/nonexistent/c.toml"], "config file /nonexistent/c.toml does not exist"),
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


@pytest.mark.parametrize("damage", ["delete", "corrupt", "other_run", "unreadable", "swapped"])
def test_resume_refuses_a_bad_key_file(capsys, tmp_path: Path, damage: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "r"
    assert _call(capsys, RUN + ["--warmup", "2", "--iterations", "0", "--final-episodes", "0", "--out", str(out)])[0] == 0
    key = out / "secrets.key"
    db_before = (out / "run.sqlite").read_bytes()
    if damage == "delete":
        key.unlink()
    elif damage == "corrupt":
        key.write_text("{not json")
    elif damage == "unreadable":  # tests run as root, so chmod 000 would not stop a read: a directory does
        key.unlink()
        key.mkdir()
    elif damage == "swapped":  # the right run id, other secrets: caught by the store's fingerprint
        doc = json.loads(key.read_text())
        doc["c"] = doc["c"] * 1.5
        key.write_text(json.dumps(doc))
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


@pytest.mark.parametrize(
    "text,needle",
    [
        ("env = 'CartPole'\nwarmup = [", "is not valid TOML"),
        ("env = 'CartPole'\nwarmpu = 3", "unknown key 'warmpu'"),
        ("env = 'CartPole'\nwarmup = 'three'", "warmup must be an integer"),
        ("env = 'CartPole'\nmethod = 'secret'", "method must be one of"),
        ("env = 'CartPole'\nbox = [1, 'a']", "box = [1, 'a'] is not a valid value"),
        ("env = 'CartPole'\nencode-params = 'maybe'", "expected on or off"),
        ("env = 'CartPole'\nwarmup = 20000", "--warmup must be <= 10000"),
        ("env = 'CartPole'\non-llm-failure = 'retry'", "on-llm-failure must be one of stop, skip"),
    ],
)
def test_malformed_config_file(capsys, tmp_path: Path, text: str, needle: str) -> None:  # type: ignore[no-untyped-def]
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    code, err = _call(capsys, ["run", "--quiet", "--out", str(tmp_path / "r"), "--config", str(cfg)])
    assert code == 2 and err.count("\n") == 1 and err.startswith("ppprops: error:") and needle in err, err
    assert not (tmp_path / "r").exists()


def test_config_file_values_are_used_and_flags_win(capsys, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        "env = 'CartPole'\nmethod = 'pe'\nwarmup = 2\niterations = 0\nfinal-episodes = 0\ntop_k = 4\n"
        "box = [-3, 3]\nscale-rewards = true\non-llm-failure = 'skip'\nretries = 7\nquiet = true\n"
    )
    out = tmp_path / "r"
    assert _call(capsys, ["run", "--config", str(cfg), "--warmup", "3", "--out", str(out)])[0] == 0
    from ppprops.store import open_store

    store = open_store(out)
    c = store.config()
    store.close()
    assert (c["method"], c["warmup"], c["iterations"], c["top_k"], c["box"]) == ("pe", 3, 0, 4, [-3.0, 3.0])
    assert c["mechanisms"]["scale_rewards"] is True and c["on_llm_failure"] == "skip" and c["llm"]["transport_retries"] == 7


def test_full_disk_during_a_run_is_one_line_and_resumable(capsys, tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import sqlite3

    from ppprops.store import RunStore, open_store

    real_init = RunStore.__init__

    def small_disk(self: RunStore, path: Path) -> None:  # SQLite's own page limit: real SQLITE_FULL errors
        real_init(self, path)
        pages = self._db.execute("PRAGMA page_count").fetchone()[0]
        self._db.execute(f"PRAGMA max_page_count = {pages + 2}")

    monkeypatch.setattr(RunStore, "__init__", small_disk)
    out = tmp_path / "r"
    code, err = _call(capsys, RUN + ["--warmup", "300", "--iterations", "0", "--final-episodes", "0", "--out", str(out)])
    assert code == 2 and err.count("\n") == 1 and "the disk is full" in err, err
    monkeypatch.undo()
    with sqlite3.connect(out / "run.sqlite") as con:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        idx = [r[0] for r in con.execute("SELECT idx FROM candidates ORDER BY idx")]
    assert 0 < len(idx) < 300 and idx == list(range(len(idx)))
    assert _call(capsys, ["resume", str(out), "--quiet"])[0] == 0
    store = open_store(out)
    assert len(store.candidates()) == 300 and store.status() == "finished"
    store.close()


def test_no_space_for_the_policy_file_is_one_line_and_resumable(capsys, tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import errno

    import ppprops.finalizing

    def full(path: Path, doc: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ppprops.finalizing, "write_json_atomic", full)
    out = tmp_path / "r"
    code, err = _call(capsys, RUN + ["--warmup", "2", "--iterations", "0", "--final-episodes", "2", "--out", str(out)])
    assert code == 2 and err.count("\n") == 1 and "No space left on device" in err and "ppprops resume" in err
    assert not (out / "best_policy.json").exists()
    monkeypatch.undo()
    assert _call(capsys, ["resume", str(out), "--quiet"])[0] == 0
    assert (out / "best_policy.json").exists()


def _pendulum_policy_doc() -> dict:  # type: ignore[type-arg]
    from ppprops.policy_file import policy_document
    from ppprops.tasks import load_task

    task = load_task("Pendulum-v1")
    env = task.make_env()
    try:
        return policy_document(task, np.zeros(task.D), env=env, search={}, final_eval=None)
    finally:
        env.close()


@pytest.mark.parametrize(
    "edit,needle",
    [
        (lambda d: d.pop("action_type"), 'action_type must be "discrete" or "continuous"'),
        (lambda d: d.update(action_type="multi-binary"), 'action_type must be "discrete" or "continuous"'),
        (lambda d: d["action"].pop("low"), "a continuous action needs numeric low and high bounds of length n_a = 1"),
        (lambda d: d["action"].update(high=[2.0, 2.0]), "a continuous action needs numeric low and high bounds of length n_a = 1"),
        (lambda d: d["action"].update(low=["a"]), "a continuous action needs numeric low and high bounds of length n_a = 1"),
        (lambda d: d["action"].update(low=[3.0]), "the action bounds have low > high"),
        (lambda d: d["action"].update(rule="argmax"), "the action block's rule must be 'clip' for action_type 'continuous'"),
        (lambda d: d.update(action_type="discrete"), "the action block's rule must be 'argmax' for action_type 'discrete'"),
        (lambda d: d.pop("env"), "the env block is missing or not an object"),
        (lambda d: d.update(observation=7), "the observation block is missing or not valid"),
        # a value of the wrong type is named as such, not as a missing key
        (lambda d: d.update(W=[["x"], [1.0], [2.0]]), "W and b must hold numbers only"),
        (lambda d: d.update(n_s="three"), "n_s and n_a must be whole numbers"),
        (lambda d: d.pop("b"), "lacks b"),
    ],
)
def test_policy_file_with_a_broken_action_block_is_one_line(capsys, tmp_path: Path, edit, needle: str) -> None:  # type: ignore[no-untyped-def]
    """A hand-edited policy file whose action block does not fit its action type (no bounds, bounds of
    the wrong length or order, the other type's rule) is refused with one line, never a KeyError."""
    from ppprops.errors import PPPropsError
    from ppprops.policy_file import load_policy

    doc = _pendulum_policy_doc()
    path = tmp_path / "p.json"
    path.write_text(json.dumps(doc))
    assert load_policy(path)(np.zeros(3)).shape == (1,)  # the untouched file is a valid policy
    edit(doc)
    path.write_text(json.dumps(doc))
    code, err = _call(capsys, ["policy", "eval", str(path), "--episodes", "1"])
    assert code == 2 and needle in err and err.count("\n") == 1 and "Traceback" not in err
    with pytest.raises(PPPropsError, match="policy file"):
        load_policy(path)


def test_policy_show_on_a_folder_that_is_not_a_run(capsys, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """A plain folder is named as not a run directory (as show, audit and resume say), not as unreadable JSON."""
    code, err = _call(capsys, ["policy", "show", str(tmp_path)])
    assert code == 2 and err.count("\n") == 1
    assert f"{tmp_path} is not a ppprops run directory (no run.sqlite) nor a policy file" in err
