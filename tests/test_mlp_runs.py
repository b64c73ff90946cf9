"""MLP searches end to end, with the offline stand-in for the LLM: from Python and from the shell a
search of ``mlp:16`` ends with a policy file that numpy and gymnasium alone evaluate to the return
``ppprops policy show`` reports; the audit checks the run; ask/tell from the shell, resume and a
mismatched policy file."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_deploy import HARNESS, readme_recipe

import ppprops
from ppprops.cli import main
from ppprops.privacy.audit import audit_run
from ppprops.seeding import final_eval_seeds
from ppprops.store import open_store

from support import offline_llm

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _numpy_only_returns(tmp_path: Path, policy_file: Path, seeds: list[int]) -> list[float]:
    """The README's recipe run where ppprops cannot be imported, on ``policy_file`` for each seed."""
    (tmp_path / "recipe.py").write_text(readme_recipe())
    (tmp_path / "cases.json").write_text(json.dumps([{"task": "t", "dir": str(policy_file.parent), "seeds": seeds}]))
    (tmp_path / "harness.py").write_text(HARNESS)
    out = subprocess.run([sys.executable, str(tmp_path / "harness.py"), str(tmp_path / "recipe.py"), str(tmp_path / "cases.json")],
                         capture_output=True, text=True, timeout=300, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})  # fmt: skip
    assert out.returncode == 0, out.stderr
    return [float(r) for r in json.loads(out.stdout.splitlines()[-1])["t"]]


def _final_seeds(doc: dict) -> list[int]:  # type: ignore[type-arg]
    """The final evaluation's episode seeds, as ``policy eval --seed`` rebuilds them from the file."""
    return [int(s) for s in final_eval_seeds(doc["final_eval"]["seed"], doc["final_eval"]["episodes"])]


def _show(path: Path, capsys: pytest.CaptureFixture[str]) -> dict:  # type: ignore[type-arg]
    assert main(["policy", "show", str(path)]) == 0
    return json.loads(capsys.readouterr().out)  # type: ignore[no-any-return]


def test_a_python_search_of_an_mlp_deploys_with_numpy_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with offline_llm():
        result = ppprops.search("Pendulum-v1", method="pp", policy={"kind": "mlp", "hidden": [16]}, warmup=4, iterations=4, seed=3,
                                out=tmp_path / "py", evaluation={"final_episodes": 3, "select_top": 2, "select_episodes": 1},
                                prompt={"form": "chat"})  # fmt: skip
    assert result.status == "finished" and result.final is not None and result.policy is not None
    assert [W.shape for W, _ in result.policy.layers] == [(3, 16), (16, 1)] and len(result.policy.theta) == 81
    doc = _show(tmp_path / "py" / "best_policy.json", capsys)
    assert doc["format"] == "ppprops.mlp_policy/1" and doc["policy"] == {"kind": "mlp", "hidden": [16], "activation": "tanh"}
    assert doc["forward"].startswith("h_0 = s; h_l = act(h_{l-1} @ W_l + b_l)")
    returns = _numpy_only_returns(tmp_path, tmp_path / "py" / "best_policy.json", _final_seeds(doc))
    assert returns == pytest.approx(list(result.final.returns), abs=1e-9)
    assert float(np.mean(returns)) == pytest.approx(doc["final_eval"]["mean"], abs=1e-9)
    # the prompts described the network and sent encoded values only
    with open_store(tmp_path / "py") as store:
        bodies = [c["request"] for c in store.llm_calls()]
    assert bodies and all("multilayer perceptron) with 2 layers" in b and "params has 81 entries" in b for b in bodies)
    report = audit_run(tmp_path / "py", simulate=False)
    assert report.leaks == [] and report.unverified == []
    assert report.checked["params"] > 0 and report.checked["params"] % 81 == 0 and report.checked["return"] > 0


def test_a_shell_search_of_an_mlp_deploys_and_resumes_ask_tell(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "shell"
    with offline_llm():
        assert main(["run", "--env", "Pendulum-v1", "--policy", "mlp:16", "--warmup", "3", "--iterations", "3", "--seed", "4",
                     "--final-episodes", "2", "--select-top", "0", "--out", str(run), "--quiet"]) == 0  # fmt: skip
    capsys.readouterr()
    doc = _show(run / "best_policy.json", capsys)
    returns = _numpy_only_returns(tmp_path, run / "best_policy.json", _final_seeds(doc))
    assert float(np.mean(returns)) == pytest.approx(doc["final_eval"]["mean"], abs=1e-9)
    assert main(["policy", "eval", str(run / "best_policy.json"), "--episodes", "2", "--seed", str(doc["search"]["seed"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["returns"] == pytest.approx(returns, abs=1e-9)

    # ask/tell from the shell, a restart in between (a second process would load the study the same way)
    study = tmp_path / "study"
    assert main(["study", "create", "--env", "Pendulum-v1", "--policy", "mlp:4", "--activation", "relu", "--method", "cmaes",
                 "--warmup", "2", "--iterations", "2", "--final-episodes", "0", "--select-top", "0", "--out", str(study)]) == 0  # fmt: skip
    capsys.readouterr()
    told = []
    for _ in range(4):
        assert main(["ask", str(study)]) == 0
        trial = json.loads(capsys.readouterr().out)
        assert trial["policy"] == {"kind": "mlp", "hidden": [4], "activation": "relu"} and "W" not in trial
        assert [np.asarray(layer["W"]).shape for layer in trial["layers"]] == [(3, 4), (4, 1)]
        assert main(["ask", str(study)]) == 0  # asked again: the same pending trial
        assert json.loads(capsys.readouterr().out)["theta"] == trial["theta"]
        ret = -float(np.sum(np.square(trial["theta"])))
        assert main(["tell", str(study), str(trial["trial"]), "--return", repr(ret)]) == 0
        capsys.readouterr()
        told.append(ret)
    with ppprops.load_study(study) as s:
        assert s.done and s.task.policy.hidden == (4,) and s.task.D == 21
        assert [c.ret for c in s.trials] == pytest.approx(told)


def test_a_policy_file_whose_layers_do_not_fit_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "r"
    ppprops.search("Pendulum-v1", method="random", policy="mlp:4", warmup=2, iterations=1, seed=1, out=run,
                   evaluation={"final_episodes": 1, "select_top": 0})  # fmt: skip
    doc = json.loads((run / "best_policy.json").read_text())
    doc["layers"][0]["W"] = [row[:3] for row in doc["layers"][0]["W"]]  # 3x3 where the env needs 3x4
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    assert main(["policy", "eval", str(bad), "--episodes", "1"]) == 2
    assert capsys.readouterr().err == (f"ppprops: error: policy file {bad}: layer 1 must have W 3x4 and b of length 4 (policy mlp:4 "
                                       "(tanh), n_s=3, n_a=1), got W 3x3 and b of length 4\n")  # fmt: skip
