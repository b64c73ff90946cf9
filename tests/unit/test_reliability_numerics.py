"""Numerical faults: a policy that drives the environment to NaN or Inf observations or rewards
ends that episode, is marked, and never poisons the prompt history or the choice of the best."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from ppprops.cli import main
from ppprops.client.codec import Codec, encode_feedback
from ppprops.client.context import prompt_context
from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig
from ppprops.evaluation import Feedback
from ppprops.loop import best_candidate
from ppprops.proposers import LLMProposer
from ppprops.proposers.llm import LLMSearch
from ppprops.runner import start
from ppprops.seeding import Streams
from ppprops.store import Candidate, open_store
from ppprops.tasks import get_task
from ppprops.testing.fault_server import FaultConfig, FaultServer

from support import make_config

ENV_ID = "PPPropsNaNCartPole-v0"
NON_FINITE = re.compile(r"(?<![A-Za-z])-?(nan|inf|infinity)(?![A-Za-z])", re.IGNORECASE)


MODES: dict[int, int] = {}  # episode seed -> fault, in the order the seeds first come


class NaNCartPole(gym.Wrapper):  # type: ignore[type-arg]
    """CartPole whose episode seed picks a fault: NaN observation, NaN reward, rewards that
    overflow the return to +inf, or none. The episode seeds are keyed by the run's fresh secrets,
    so the fault goes by the order a seed first comes (0, 1, 2, none, 0, ...), not by its value:
    every run meets all three faults."""

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        self.mode = MODES.setdefault(seed or 0, len(MODES) % 4)
        self.t = 0
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> Any:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.t += 1
        if self.t >= 3:
            if self.mode == 0:
                obs = np.full_like(obs, np.nan)
            elif self.mode == 1:
                reward = float("nan")
            elif self.mode == 2:
                reward = 1e308  # finite each step; the sum overflows to inf
        return obs, reward, terminated, truncated, info


def _task_name() -> str:
    """The wrapped env as a generic Gymnasium task (nothing added to ppprops' own task list)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point=lambda **kw: NaNCartPole(gym.make("CartPole-v1", **kw)))
    return get_task(ENV_ID).name


def test_nan_and_inf_never_reach_the_prompt_or_the_best(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    task = _task_name()
    MODES.clear()
    out = tmp_path / "r"
    with FaultServer(FaultConfig(fault_rate=0.0)) as server:
        llm = LLMConfig(base_url=server.base_url, model="m", structured="json_schema", timeout_s=5.0)
        start(make_config(task=task, warmup=12, iterations=6, final_episodes=2, top_k=0, llm=llm), out)
    store = open_store(out)
    cands, calls, fe = store.candidates(), store.llm_calls(), store.final_eval()
    store.close()
    rets = [c.ret for c in cands]
    # the evaluator stops an episode at the step whose reward would overflow the sum, so every
    # return stays finite and each injected fault (all three kinds) is marked
    assert all(math.isfinite(r) for r in rets)
    faulty = [c for c in cands if c.feedback.diagnostics.get("numerical_fault")]
    assert len(faulty) >= 3
    assert {MODES[c.seeds[0]] for c in faulty} == {0, 1, 2}
    assert {c.index for c in faulty} == {c.index for c in cands if MODES[c.seeds[0]] != 3}  # marked exactly when faulty
    prompts = [m["content"] for call in calls for m in json.loads(call["request"])["messages"]]
    assert len(prompts) >= 6
    for p in prompts:
        assert not NON_FINITE.search(p), NON_FINITE.search(p)
    best = best_candidate(cands)
    assert math.isfinite(best.ret) and best.ret == max(r for r in rets if math.isfinite(r))
    assert fe is not None and fe.candidate_index == best.index
    assert math.isfinite(json.loads((out / "best_policy.json").read_text())["search"]["return"])

    assert main(["show", str(out), "--json"]) == 0
    text = capsys.readouterr().out

    def strict(const: str) -> None:
        raise ValueError(f"non-standard JSON constant {const}")

    s = json.loads(text, parse_constant=strict)  # show --json stays valid JSON
    assert s["counts"]["numerical_faults"] >= 3 and s["best"]["index"] == best.index


def test_non_finite_feedback_is_kept_out_of_the_history() -> None:
    cartpole = get_task("CartPole")
    config = make_config(method="pp")
    secrets = Secrets.generate("r", cartpole.D)
    codec = Codec(secrets, encode_params=True, scale_rewards=True)
    proposer = LLMProposer(LLMSearch(llm=None, codec=codec, context=prompt_context(cartpole, config.prompt, codec), top_k=0,  # type: ignore[arg-type]
                                     box=(-6.0, 6.0), streams=Streams(0)))

    def cand(i: int, ret: float, comps: dict[str, float], diags: dict[str, Any]) -> Candidate:
        fb = Feedback(ret=ret, components=comps, diagnostics=diags, episode_returns=(ret,))
        theta = np.full(cartpole.D, 0.1 * i)
        return Candidate(i, i, "warmup", theta, codec.encode(theta), fb, encode_feedback(codec, fb), 0, (i,))

    proposer.tell(cand(0, 10.0, {"alive": float("nan"), "ctrl": 1.0}, {"height": float("inf"), "episode_length": 10.0}))
    proposer.tell(cand(1, float("inf"), {}, {}))
    proposer.tell(cand(2, float("nan"), {}, {}))
    proposer.tell(cand(3, 5.0, {}, {"termination": "pole_fell"}))
    assert [e.index for e in proposer.entries] == [0, 3] and proposer.nonfinite_skipped == 2
    assert proposer.best is not None and proposer.best.index == 0
    (e0,) = [e for e in proposer.entries if e.index == 0]
    assert dict(e0.components) == {"ctrl": codec.scale(1.0)} and dict(e0.diagnostics)["height"] == "non-finite"
    assert not NON_FINITE.search(proposer.prompt())
