"""Random search and CMA-ES at the PP-ProPS budget, through the same loop, store and CLI."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.methods import Mechanisms
from ppprops.proposers.cmaes import CMAESProposer
from ppprops.runner import resume, start
from ppprops.store import open_store

from support import make_config


def _bb_config(method: str, encoded: bool = False, **kw: object):  # type: ignore[no-untyped-def]
    cfg = make_config("CartPole", "pp", warmup=5, iterations=12, final_episodes=2, **kw)
    return replace(cfg, method=method, mechanisms=Mechanisms(encoded, encoded, False, False, False))


@pytest.mark.parametrize("method", ["random", "cmaes"])
def test_cli_runs_and_show_lists_the_sources(tmp_path: Path, capsys, method: str) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / method
    assert main(["run", "--env", "CartPole", "--method", method, "--warmup", "4", "--iterations", "8",
                 "--final-episodes", "2", "--select-top", "0", "--out", str(out), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["show", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["method"] == method and len(s["candidates"]) == 12 and s["llm_calls"] == []
    assert [c["source"] for c in s["candidates"]] == ["warmup"] * 4 + [method] * 8
    assert all(-6 <= v <= 6 for c in s["candidates"] for v in c["params"])
    assert (out / "best_policy.json").exists()


def test_random_search_continues_the_uniform_stream(tmp_path: Path) -> None:
    start(_bb_config("random"), tmp_path / "r")
    cands = open_store(tmp_path / "r").candidates()
    flat = np.concatenate([c.params for c in cands])
    assert len({tuple(c.params) for c in cands}) == len(cands)  # no sample repeats the warm-up's
    assert flat.min() >= -6 and flat.max() <= 6 and abs(flat.mean()) < 1.0


@pytest.mark.parametrize("encoded", [False, True])
def test_cmaes_resumes_into_the_same_sequence(tmp_path: Path, monkeypatch, encoded: bool) -> None:  # type: ignore[no-untyped-def]
    from ppprops.client.secrets import Secrets

    secrets = Secrets(run_id="cma", a=np.linspace(0.2, 5.0, 10), c=2.5)
    start(_bb_config("cmaes", encoded), tmp_path / "full", secrets=secrets)
    full = open_store(tmp_path / "full").candidates()

    real_ask = CMAESProposer.ask
    calls = {"n": 0}

    def crash_on_9th(self, iteration):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 9:  # mid-population (pycma's default popsize is 10 for D=10)
            raise KeyboardInterrupt
        return real_ask(self, iteration)

    monkeypatch.setattr(CMAESProposer, "ask", crash_on_9th)
    with pytest.raises(KeyboardInterrupt):
        start(_bb_config("cmaes", encoded), tmp_path / "cut", secrets=secrets)
    assert len(open_store(tmp_path / "cut").candidates()) == 5 + 8
    monkeypatch.setattr(CMAESProposer, "ask", real_ask)
    resume(tmp_path / "cut")
    cut = open_store(tmp_path / "cut").candidates()
    assert len(cut) == len(full) == 17
    for a, b in zip(full, cut):
        np.testing.assert_array_equal(a.params, b.params)
        assert a.ret == b.ret


def test_cmaes_improves_on_its_warmup(tmp_path: Path) -> None:
    cfg = replace(_bb_config("cmaes"), iterations=40)
    start(cfg, tmp_path / "c")
    cands = open_store(tmp_path / "c").candidates()
    warm = max(c.ret for c in cands if c.source == "warmup")
    assert max(c.ret for c in cands) > warm
