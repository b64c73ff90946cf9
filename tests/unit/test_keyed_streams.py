"""No public randomness reaches a prompt: every stream that shapes what the
provider sees (warm-up, episode seeds and so initial states, fallback noise) is keyed by the run's
secrets, so the run seed read off a transcript gives nothing; a run stays reproducible from its key file.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppprops import seeding
from ppprops.client.hardening import generate_secrets
from ppprops.client.secrets import Secrets
from ppprops.privacy.attacks import find_run_seed
from ppprops.privacy.requests import load_requests
from ppprops.privacy.simulate import EchoOptimizer
from ppprops.privacy.view import view_of
from ppprops.store import open_store
from ppprops.study import Study

from support import make_config


def seeded_secrets(config: Any, k: int) -> Any:
    """The run's secret distribution, from a seeded generator so the test repeats."""
    return generate_secrets(f"keyed-{config.method}-{k}", config.make_task(), config.encoding, rng=np.random.default_rng(k))


def _run(tmp_path: Path, name: str, method: str, *, keyed: bool = True, seed: int = 0, secrets_seed: int = 1) -> Path:
    config = make_config("CartPole", method, warmup=6, iterations=3, final_episodes=0, seed=seed)
    with Study.create(config, tmp_path / name, secrets=seeded_secrets(config, secrets_seed)) as study:
        if not keyed:  # as a run recorded before streams were keyed: from the run seed alone
            with sqlite3.connect(tmp_path / name / "run.sqlite") as db:
                db.execute("DELETE FROM meta WHERE key = 'streams'")
        study.store.close()
    with Study.load(tmp_path / name, llm=EchoOptimizer(config.llm)) as study:
        study.optimize()
    return tmp_path / name


@pytest.mark.parametrize("method", ["pp-hardened", "pp"])
def test_the_run_seed_cannot_be_read_off_a_transcript(tmp_path: Path, method: str) -> None:
    legacy = view_of(load_requests(_run(tmp_path, "legacy", method, keyed=False)), "CartPole", (-6.0, 6.0))
    assert find_run_seed(legacy)[0] == 0  # the unkeyed warm-up gives the run seed away (the red team's finding)
    new = view_of(load_requests(_run(tmp_path, "new", method)), "CartPole", (-6.0, 6.0))
    seed, how = find_run_seed(new)
    assert seed is None and "none matches" in how


def test_the_streams_depend_on_the_key_and_repeat_for_the_same_key(tmp_path: Path) -> None:
    runs = [_run(tmp_path, name, "pp", secrets_seed=k) for name, k in (("a", 1), ("b", 2), ("a2", 1))]
    cands = []
    for r in runs:
        with open_store(r) as store:
            assert store.streams_keyed()
            cands.append(store.candidates())
    warm = [np.array([c.params for c in cs if c.source == "warmup"]) for cs in cands]
    seeds = [[c.seeds for c in cs] for cs in cands]
    assert not np.allclose(warm[0], warm[1]) and seeds[0] != seeds[1]  # same run seed, other key: other draws
    assert np.array_equal(warm[0], warm[2]) and seeds[0] == seeds[2]  # same key file: the same run
    assert not np.allclose(warm[0][0], seeding.rng(0, seeding.WARMUP, 0).uniform(-6, 6, size=10))


def test_a_keyed_study_keeps_its_streams_when_resumed(tmp_path: Path) -> None:
    config = make_config("CartPole", "random", warmup=4, iterations=4, final_episodes=0, seed=5)
    secrets = seeded_secrets(config, 3)
    with Study.create(config, tmp_path / "whole", secrets=secrets) as study:
        study.optimize()
        whole = study.trials
    with Study.create(config, tmp_path / "halves", secrets=secrets) as study:
        for _ in range(3):
            t = study.ask()
            study.tell(t, feedback=study.evaluator.evaluate(t.theta, t.seeds))
    with Study.load(tmp_path / "halves") as study:  # another process, the same key file
        study.optimize()
        halves = study.trials
    assert [(c.index, c.seeds, c.ret) for c in whole] == [(c.index, c.seeds, c.ret) for c in halves]
    assert all(np.array_equal(a.params, b.params) for a, b in zip(whole, halves, strict=True))


@pytest.mark.parametrize("hardened", [False, True])
def test_secrets_drawn_from_a_seeded_generator_are_the_same_whatever_numpy_exp_gives(monkeypatch: pytest.MonkeyPatch,
                                                                                    hardened: bool) -> None:
    """A grid's master key (or any seeded generator) must give the same secrets, hence the same keyed
    draws, on every machine; numpy's exp differs in the last bits between builds. Here exp is made
    one ulp larger: the secrets, and every subkey hashed from them, stay the same."""
    def draw() -> Secrets:
        rng = np.random.default_rng(11)
        if hardened:
            return Secrets.generate_hardened("h", 12, box=(-6.0, 6.0), reward_scale=1000.0, rng=rng)
        return Secrets.generate("p", 12, rng=rng)

    exact = draw()
    real_exp = np.exp
    monkeypatch.setattr(np, "exp", lambda x: np.nextafter(real_exp(x), np.inf))
    shifted = draw()
    assert np.array_equal(exact.a, shifted.a) and exact.c == shifted.c and exact.p == shifted.p
    assert exact.subkey("sampling-seed") == shifted.subkey("sampling-seed")
    assert all(float(f"{v:.12g}") == v for v in exact.a)  # what makes them portable: 12 significant digits
