"""Short runs with fixed seeds, fixed secrets and a fixed chat, and what of them is pinned.

Shared by tests/data/make_golden_study.py (which writes tests/data/golden_study.json) and
tests/test_study.py (which reruns each case and compares).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from ppprops.client.hardening import generate_secrets
from ppprops.privacy.simulate import EchoOptimizer
from ppprops.settings import build_config
from ppprops.store import open_store
from ppprops.tasks import get_task

# name -> (task, settings); every case: CartPole, 4 warm-up + 6 proposals, 3 final episodes.
CASES: dict[str, dict[str, Any]] = {
    "pp-document": {"method": "pp"},
    "pp-chat": {"method": "pp", "prompt_form": "chat"},
    "pp-hardened": {"method": "pp-hardened"},
    "vanilla-2ep": {"method": "vanilla", "prompt_form": "chat", "episodes": 2},
    "random": {"method": "random"},
    "cmaes": {"method": "cmaes"},
    "r2po": {"method": "r2po", "episodes": 2, "iterations": 4},
}


def case_config(name: str) -> Any:
    values = {"warmup": 4, "iterations": 6, "final_episodes": 3, "seed": 7, **CASES[name]}
    return build_config(values, task=get_task("CartPole"))


def case_secrets(name: str, config: Any) -> Any:
    """The case's fixed secrets, rounded to 9 decimals: drawn through numpy's exp, whose last bits
    vary between numpy builds, and every keyed draw hashes the secrets' exact values."""
    rng = np.random.default_rng(sum(map(ord, name)))  # fixed per case
    s = generate_secrets(f"golden-{name}", get_task("CartPole"), config.encoding, rng=rng)
    return dataclasses.replace(s, a=np.round(s.a, 9), c=round(float(s.c), 9),
                               m=None if s.m is None else np.round(s.m, 9), s=None if s.s is None else round(float(s.s), 9),
                               p=None if s.p is None else round(float(s.p), 9))


def run_case(name: str, run_dir: Path) -> None:
    """Run one case to the end in ``run_dir`` (must not exist yet)."""
    from ppprops.runner import start

    config = case_config(name)
    start(config, run_dir, secrets=case_secrets(name, config), llm=EchoOptimizer(config.llm, spread=0.5))


def golden_record(run_dir: Path) -> dict[str, Any]:
    """What is pinned of a finished run: every candidate, every recorded request body, the final evaluation."""
    with open_store(run_dir) as store:
        cands = store.candidates()
        calls = store.llm_calls()
        fe = store.final_eval()
    return {
        "candidates": [
            {"index": c.index, "iteration": c.iteration, "source": c.source, "params": [round(float(v), 10) for v in c.params],
             "params_enc": [round(float(v), 8) for v in c.params_enc], "ret": c.ret, "ret_enc": round(c.feedback_enc.ret, 8),
             "seeds": list(c.seeds), "note": c.note, "clipped": c.clipped}
            for c in cands
        ],
        "requests": [json.loads(r["request"]) for r in calls],
        "parse_errors": [r["parse_error"] for r in calls],
        "final": None if fe is None else {"candidate": fe.candidate_index, "returns": list(fe.returns), "seeds": list(fe.seeds)},
    }
