"""`ppprops resume DIR --base-url ... --model ... --api-key-env ...` continues a run against a
corrected or different endpoint; the change is recorded in the run, the secrets stay the same."""

from __future__ import annotations

import json
from pathlib import Path

from ppprops.cli import main
from ppprops.store import open_store
from ppprops.testing.fault_server import FaultConfig, FaultServer


def _call(capsys, args: list[str]) -> tuple[int, str, str]:  # type: ignore[no-untyped-def]
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_a_wrong_url_is_corrected_on_resume(tmp_path: Path, capsys, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    monkeypatch.setenv("PPPROPS_RIGHT_KEY", "sk-resume-secret-123")
    with FaultServer(FaultConfig(fault_rate=0.0)) as server:
        wrong = server.base_url + "/chat/completions"  # a common mistake: the full route instead of the root
        code, _, err = _call(capsys, ["run", "--env", "CartPole", "--method", "pp", "--warmup", "3", "--iterations", "4",
                                      "--final-episodes", "2", "--select-top", "0", "--base-url", wrong, "--model", "m",
                                      "--out", str(out), "--quiet"])  # fmt: skip
        assert code == 2 and f"ppprops resume {out}" in err and err.count("\n") == 1
        store = open_store(out)
        warmup = [(c.index, c.params.tolist()) for c in store.candidates()]
        fingerprint = store.key_fingerprint()
        store.close()
        assert len(warmup) == 3  # stopped right after the warm-up
        key_before = (out / "secrets.key").read_bytes()
        seen_before = server.stats()["requests"]

        code, _, err = _call(capsys, ["resume", str(out), "--base-url", server.base_url, "--api-key-env", "PPPROPS_RIGHT_KEY",
                                      "--quiet"])  # fmt: skip
        assert code == 0, err
        assert server.stats()["requests"] - seen_before >= 4  # the LLM phase went to the corrected URL

    store = open_store(out)
    try:
        done = store.candidates()
        assert [c.index for c in done] == list(range(7)) and store.status() == "finished"
        assert [(c.index, c.params.tolist()) for c in done[:3]] == warmup
        assert store.key_fingerprint() == fingerprint
    finally:
        store.close()
    assert (out / "secrets.key").read_bytes() == key_before
    assert b"sk-resume-secret-123" not in (out / "run.sqlite").read_bytes()  # the variable's name is stored, never the key

    code, text, _ = _call(capsys, ["show", str(out), "--json"])
    s = json.loads(text)
    assert s["config"]["llm"]["base_url"] == server.base_url and s["config"]["llm"]["api_key_env"] == "PPPROPS_RIGHT_KEY"
    [change] = s["endpoint_changes"]
    assert change["from"] == {"base_url": wrong, "model": "m", "api_key_env": None}
    assert change["to"] == {"base_url": server.base_url, "model": "m", "api_key_env": "PPPROPS_RIGHT_KEY"}
    assert change["candidates"] == 3
    code, text, _ = _call(capsys, ["show", str(out)])
    line = f"endpoint changed on resume after 3 candidates: {wrong} (m) -> {server.base_url} (m, key from $PPPROPS_RIGHT_KEY)"
    assert line in text.splitlines()


def test_a_bad_endpoint_on_resume_is_one_line_and_changes_nothing(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    assert main(["run", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "1", "--final-episodes", "0", "--select-top", "0",
                 "--out", str(out), "--quiet"]) == 0  # fmt: skip
    capsys.readouterr()
    db_before = (out / "run.sqlite").read_bytes()
    for args, needle in ((["--base-url", "localhost:8000/v1"], "must start with http"),
                         (["--base-url", "http://127.0.0.1:9/v1"], "--model is required")):  # an embedded run has no model to keep
        code, _, err = _call(capsys, ["resume", str(out), *args, "--quiet"])
        assert code == 2 and needle in err and err.count("\n") == 1
    assert (out / "run.sqlite").read_bytes() == db_before


def test_switching_to_another_model_is_recorded(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    with FaultServer(FaultConfig(fault_rate=0.0)) as a, FaultServer(FaultConfig(fault_rate=0.0, seed=1)) as b:
        # stop after two LLM iterations: the first endpoint's budget is three requests, then it answers 503
        args = ["run", "--env", "CartPole", "--method", "pp", "--warmup", "2", "--iterations", "4", "--final-episodes", "0", "--select-top", "0",
                "--base-url", a.base_url, "--model", "first", "--retries", "0", "--out", str(out), "--quiet"]  # fmt: skip
        a.config.max_requests = 2
        assert _call(capsys, args)[0] == 2
        assert _call(capsys, ["resume", str(out), "--base-url", b.base_url, "--model", "second", "--quiet"])[0] == 0
        assert b.stats()["requests"] >= 2
    s = json.loads(_call(capsys, ["show", str(out), "--json"])[1])
    [change] = s["endpoint_changes"]
    assert (change["from"]["model"], change["to"]["model"], change["candidates"]) == ("first", "second", 4)
    assert [c["index"] for c in s["candidates"]] == list(range(6))
    bodies = [json.loads(r[0]) for r in _requests(out)]
    assert [b_["model"] for b_ in bodies] == ["first", "first", "first", "second", "second"]


def _requests(out: Path) -> list[tuple[str]]:
    import sqlite3

    with sqlite3.connect(out / "run.sqlite") as con:
        return con.execute("SELECT request FROM llm_calls ORDER BY id").fetchall()
