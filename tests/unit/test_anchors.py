"""Anchored returns: a shown diagnostic that marks an episode end at a public cap pins that entry's
raw return exactly (CartPole ``termination=time_limit``: 500; Acrobot ``success=0``: -500),
whatever the reward map. The audit names it (exposed, not CLEAN); ``pp-hardened`` withholds
those diagnostics (``hide_anchors``), and then the same run audits CLEAN.

Driven through ask/tell with an offline stand-in optimizer: no model, no subprocess."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import ppprops
from ppprops import rundir
from ppprops.client import hardening
from ppprops.privacy.audit import audit_run
from ppprops.privacy.matrix import analyse_run, format_report
from ppprops.store import open_store

from support import offline_llm

CASES = {  # task: (the told feedback of trial 1, the pinned raw return; every other trial's)
    "CartPole": (lambda n: (500.0, {"episode_length": 500, "termination": "time_limit"}) if n == 1 else
                 (20.0 + n, {"episode_length": 20 + n, "termination": "pole_fell"}), "termination", 500.0),
    "Acrobot": (lambda n: (-500.0, {"episode_length": 500, "success": 0}), "success", -500.0),
}


def _audited(tmp_path: Path, task: str, hide_anchors: bool):  # type: ignore[no-untyped-def]
    told, _, _ = CASES[task]
    run_dir = tmp_path / f"{task}-{hide_anchors}"
    with offline_llm(), ppprops.create_study(task, storage=run_dir, method="pp-hardened", warmup=3, iterations=3, seed=4,
                                             prompt={"form": "chat"}, evaluation={"final_episodes": 0, "select_top": 0},
                                             privacy={"hide_anchors": hide_anchors}) as study:
        while not study.done:
            trial = study.ask()
            ret, diagnostics = told(trial.number)
            study.tell(trial, ret, diagnostics=diagnostics)
    with open_store(run_dir) as store:
        bodies = [json.loads(c["request"]) for c in store.llm_calls()]
    return audit_run(run_dir, simulate=False), bodies


@pytest.mark.parametrize("task", list(CASES))
def test_a_return_pinned_by_a_shown_diagnostic_is_never_clean_and_hide_anchors_closes_it(tmp_path: Path, task: str,
                                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    _, diagnostic, cap = CASES[task]
    # fixed secrets and run id (which keys the streams) for the verdicts: on fresh ones an attack reads a value by chance now and then
    monkeypatch.setattr(hardening, "os_rng", lambda: np.random.default_rng(3))
    monkeypatch.setattr(rundir, "new_run_id", lambda config: f"{config.task}__{config.method}__{config.seed}__20261204-000000-0000")
    old, old_bodies = _audited(tmp_path, task, hide_anchors=False)  # pp-hardened as it was: the diagnostic shown
    assert any(f"{diagnostic}=" in str(b["messages"]) for b in old_bodies)
    anchored = [f for f in old.exposed if f.kind == "anchored_return"]
    assert len(anchored) == 1 and not old.clean, old.format()
    assert f"raw return {cap:g}" in anchored[0].detail and "best shown policy's raw return" in anchored[0].detail
    assert old.verdict().startswith("EXPOSED") and old.exit_code() == 1
    new, new_bodies = _audited(tmp_path, task, hide_anchors=True)  # pp-hardened now
    assert all(diagnostic not in str(b["messages"]) for b in new_bodies)  # withheld from every request
    assert not [f for f in new.findings if f.kind == "anchored_return"]
    assert new.clean and new.verdict().startswith("CLEAN"), new.format()
    # the privacy report counts the runs a shown diagnostic pins
    runs = [analyse_run(tmp_path / f"{task}-{hide}", simulate=False) for hide in (False, True)]
    assert [r.anchored for r in runs] == [True, False]
    text = format_report(runs)
    assert "| pp-hardened | 2 |" in text and text.splitlines()[-3].endswith("| 1/2 |"), text


def test_pp_hardened_hides_anchors_by_default() -> None:
    from ppprops.methods import resolve

    assert resolve("pp-hardened").hide_anchors and not resolve("pp").hide_anchors


def test_a_near_miss_is_named_in_the_verdict_line() -> None:
    from ppprops.privacy.audit import AuditReport

    r = AuditReport("runs/x", "pp", {}, near_misses=["sim-marginal: c within 1.31%"])
    assert r.clean and r.verdict() == ("CLEAN: no raw parameter, return, reward component or optimal return was sent; "
                                       "near miss (within 2%, not 1%): sim-marginal: c within 1.31%")
    assert r.to_json()["near_misses"] == ["sim-marginal: c within 1.31%"] and r.exit_code() == 0
