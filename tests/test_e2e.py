"""Short real searches: the embedded Gemma model behind llama.cpp's HTTP server, real Gymnasium envs."""

from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path

import pytest

from ppprops.cli import main

pytestmark = pytest.mark.llm


def _run(capsys, *args: str) -> tuple[int, str, str]:  # type: ignore[no-untyped-def]
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("task,method", [("CartPole", "pp"), ("Acrobot", "df")])
def test_cli_run_show_and_policy_eval(tmp_path: Path, capsys, task: str, method: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    code, stdout, _ = _run(capsys, "run", "--env", task, "--method", method, "--warmup", "3", "--iterations", "3",
                           "--final-episodes", "4", "--select-top", "0", "--seed", "5", "--out", str(out), "--quiet")
    assert code == 0, stdout
    assert {p.name for p in out.iterdir()} >= {"run.sqlite", "secrets.key", "best_policy.json"}
    assert stat.S_IMODE(os.stat(out / "secrets.key").st_mode) == 0o600
    key = json.loads((out / "secrets.key").read_text())
    printed = set(re.findall(r"(?<![\w.])-?\d+\.\d+(?![\w.])", stdout))  # whole numbers, not digits inside others
    values = [*key["a"], key["c"]]  # the summary never prints key material
    assert not [v for v in values if f"{v:.4f}" in printed]
    # at 2 decimals one of 11 random values can equal a printed latency or return by chance; a printed
    # key prints them all
    assert len([v for v in values if f"{v:.2f}" in printed]) <= 1, (printed, values)

    code, stdout, _ = _run(capsys, "show", str(out), "--json")
    assert code == 0
    s = json.loads(stdout)
    assert s["env"] == task and s["method"] == method and s["seed"] == 5
    assert len(s["candidates"]) == 6
    assert [c["source"] for c in s["candidates"][:3]] == ["warmup"] * 3
    assert all(c["source"] in ("llm", "fallback") for c in s["candidates"][3:])
    for c in s["candidates"]:
        assert set(c) >= {"index", "iteration", "source", "params", "return", "components", "diagnostics"}
        assert all(-6.0 <= v <= 6.0 for v in c["params"])
        assert "episode_length" in c["diagnostics"]
    best = max(s["candidates"], key=lambda c: c["return"])
    assert s["best"]["return"] == best["return"]
    assert s["final_eval"]["episodes"] == 4
    assert len(s["llm_calls"]) >= 3
    for call in s["llm_calls"]:
        assert set(call) >= {"latency_s", "prompt_tokens", "completion_tokens", "prompt_chars", "ok"}
        assert call["latency_s"] > 0 and call["prompt_tokens"] > 0 and call["prompt_chars"] > 300  # the document form is short

    doc = json.loads((out / "best_policy.json").read_text())
    assert doc["task"] == task and len(doc["W"]) == doc["n_s"] and len(doc["b"]) == doc["n_a"]
    assert doc["theta"] == pytest.approx(s["candidates"][s["best"]["index"]]["params"])

    code, stdout, _ = _run(capsys, "policy", "eval", str(out / "best_policy.json"), "--episodes", "4", "--seed", "5", "--json")
    assert code == 0
    ev = json.loads(stdout)
    assert ev["mean"] == pytest.approx(s["final_eval"]["mean"]) and ev["returns"] == pytest.approx(s["final_eval"]["returns"])


def test_unbounded_history_shows_every_entry(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    code, _, _ = _run(capsys, "run", "--env", "CartPole", "--method", "vanilla", "--warmup", "12", "--iterations", "2",
                      "--top-k", "0", "--final-episodes", "0", "--select-top", "0", "--out", str(out), "--quiet")
    assert code == 0
    from ppprops.store import open_store

    store = open_store(out)
    body = json.loads(store.llm_calls()[-1]["request"])
    last = body["prompt"] if "prompt" in body else body["messages"][0]["content"]  # the embedded default: the document form
    assert last.count("\nreturn: ") >= 13  # 12 warm-up + the first LLM candidate, none dropped
