"""A short search (2 warm-up + 2 LLM iterations) on every task and a plain Gymnasium id.

With the embedded model on the low-dimensional tasks (D up to 21); on the others (D from 28 to
782) the 270M model writes D labelled numbers per answer, a token per character: about 900 tokens
and 40 s or more per request at D=88 on 2 cores, about 4,500 tokens and 5 minutes or more at
D=459 (FetchReachDense, D=28, took 89 s in all). So the normal suite runs those tasks with the
offline LLM (``ppprops.privacy.simulate``: the same runner, store, prompts and policy file, no
model), and the embedded model on them carries the slow marker (`python -m pytest -m slow`), where
each must get at least one usable answer from the model."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.tasks import get_task

from support import offline_llm

FAST = ["CartPole", "Acrobot", "MountainCarContinuous-v0"]
HIGH_D = ["FetchReachDense", "Highway-Fast", "Ant-Ultra", "Ant-Joints", "Ant-Torso", "Humanoid-Ultra", "Humanoid-Joints", "Humanoid-Torso"]
# The embedded model on the higher-dimensional tasks and Highway's default config (an episode of
# about 8 s), with a pytest timeout per task: each LLM request writes about D x 10 tokens.
SLOW = {"FetchReachDense": 600, "Highway-Fast": 900, "Ant-Ultra": 900, "Ant-Joints": 1800, "Ant-Torso": 2400, "Humanoid-Ultra": 2400,
        "Humanoid-Joints": 3600, "Humanoid-Torso": 5400, "Highway": 1200}


def _search(tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str) -> dict[str, object]:
    out = tmp_path / "run"
    task = get_task(name)
    # three history entries of D labelled numbers plus the answer must fit the model's context
    context = 32768 if task.D > 200 else 16384
    code = main(["run", "--env", name, "--method", "pp", "--warmup", "2", "--iterations", "2", "--final-episodes", "1", "--select-top", "0",
                 "--context-size", str(context), "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    capsys.readouterr()
    assert main(["show", str(out), "--json"]) == 0
    s: dict[str, object] = json.loads(capsys.readouterr().out)
    cands = s["candidates"]
    assert isinstance(cands, list) and len(cands) == 4 and s["status"] == "finished"
    assert [c["source"] for c in cands[:2]] == ["warmup", "warmup"]
    for c in cands:
        assert len(c["params"]) == task.D
        assert set(task.diagnostics) <= set(c["diagnostics"])
        assert set(task.components) == set(c["components"])
    doc = json.loads((out / "best_policy.json").read_text())
    assert len(doc["W"]) == task.n_s and len(doc["b"]) == task.n_a
    return s


@pytest.mark.llm
@pytest.mark.parametrize("name", FAST)
def test_short_pp_search_completes(tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str) -> None:
    s = _search(tmp_path, capsys, name)
    assert len(s["llm_calls"]) >= 2  # type: ignore[arg-type]


@pytest.mark.parametrize("name", HIGH_D)
def test_short_pp_search_completes_on_a_high_dimensional_task_with_the_offline_llm(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str) -> None:
    with offline_llm():
        s = _search(tmp_path, capsys, name)
    assert [c["source"] for c in s["candidates"][2:]] == ["llm", "llm"]  # type: ignore[index]


@pytest.mark.llm
@pytest.mark.parametrize("name", [pytest.param(n, marks=[pytest.mark.slow, pytest.mark.timeout(t)]) for n, t in SLOW.items()])
def test_short_pp_search_with_the_embedded_model_serves_every_task(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                    name: str) -> None:
    s = _search(tmp_path, capsys, name)
    counts = s["counts"]
    assert isinstance(counts, dict)
    # the model's answers fit the token budget and the timeout: at least one proposal is the model's
    assert counts["llm"] >= 1 and "length" not in counts["answer_failures"], counts
    assert "timeout" not in counts["transport_failures"], counts
