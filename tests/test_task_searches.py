"""A short search (2 warm-up + 2 LLM iterations, embedded model) on every task and a plain
Gymnasium id. High-dimensional tasks make the 270M model write hundreds of numbers per answer
(minutes per call on 2 cores), so they carry the slow marker: `python -m pytest -m slow`."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.tasks import get_task

FAST = ["CartPole", "Acrobot", "FetchReachDense", "Highway-Fast", "Ant-Ultra", "MountainCarContinuous-v0"]
SLOW = ["Ant-Joints", "Ant-Torso", "Humanoid-Ultra", "Humanoid-Joints", "Humanoid-Torso", "Highway"]


@pytest.mark.llm
@pytest.mark.parametrize("name", FAST + [pytest.param(n, marks=pytest.mark.slow) for n in SLOW])
def test_short_pp_search_completes(tmp_path: Path, capsys, name: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "run"
    task = get_task(name)
    # three history entries of D numbers plus a D-number answer must fit the model's context
    context = 32768 if task.D > 200 else 16384
    code = main(["run", "--env", name, "--method", "pp", "--warmup", "2", "--iterations", "2", "--final-episodes", "1", "--select-top", "0",
                 "--context-size", str(context), "--out", str(out), "--quiet"])
    assert code == 0
    capsys.readouterr()
    assert main(["show", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert len(s["candidates"]) == 4 and s["status"] == "finished"
    assert [c["source"] for c in s["candidates"][:2]] == ["warmup", "warmup"]
    assert len(s["llm_calls"]) >= 2
    for c in s["candidates"]:
        assert len(c["params"]) == task.D
        assert set(task.diagnostics) <= set(c["diagnostics"])
        assert set(task.components) == set(c["components"])
    doc = json.loads((out / "best_policy.json").read_text())
    assert len(doc["W"]) == task.n_s and len(doc["b"]) == task.n_a
