"""R2PO: the better of proposal and revision enters the history; context overflow stops cleanly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.client.codec import Codec, encode_feedback
from ppprops.client.context import prompt_context
from ppprops.client.secrets import Secrets
from ppprops.evaluation import Feedback
from ppprops.proposers.base import StopSearch
from ppprops.proposers.llm import LLMSearch
from ppprops.proposers.r2po import R2POProposer
from ppprops.seeding import Streams
from ppprops.store import Candidate, open_store
from ppprops.tasks import get_task

from support import make_config


def _proposer(window: int = 10**6) -> tuple[R2POProposer, Codec]:
    task = get_task("CartPole")
    codec = Codec(Secrets(run_id="r", a=np.ones(task.D), c=1.0), encode_params=False, scale_rewards=False)
    ctx = prompt_context(task, make_config("CartPole", "vanilla").prompt, codec)
    steps = [((0.1, 0.2, 0.3, 0.4), "1")] * 50
    run = LLMSearch(llm=None, codec=codec, context=ctx, top_k=10, box=(-6, 6), streams=Streams(0))  # type: ignore[arg-type]
    p = R2POProposer(run, rollout=lambda theta, seed: (50.0, steps), count_tokens=len, context_window=window, max_tokens=100)
    return p, codec


def _cand(codec: Codec, i: int, source: str, ret: float) -> Candidate:
    theta = np.full(10, float(i))
    fb = Feedback(ret=ret, diagnostics={"episode_length": ret}, episode_returns=(ret - 1, ret, ret + 1))
    return Candidate(i, i, source, theta, codec.encode(theta), fb, encode_feedback(codec, fb), 0, (1, 2, 3))


def _history_params(p: R2POProposer) -> list[float]:
    return [e.params[0] for e in p.search.entries]


def test_keeps_the_better_of_proposal_and_revision() -> None:
    p, codec = _proposer()
    p.tell(_cand(codec, 0, "warmup", 10.0))
    p.tell(_cand(codec, 1, "r2po-search", 30.0))
    p.tell(_cand(codec, 2, "r2po-critic", 20.0))  # revision worse: the proposal stays
    p.tell(_cand(codec, 3, "r2po-search", 15.0))
    p.tell(_cand(codec, 4, "r2po-critic", 40.0))  # revision better: it replaces the proposal
    assert _history_params(p) == [0.0, 1.0, 4.0]
    assert p.search.best is not None and p.search.best.index == 4
    prompt = p.search.prompt()
    assert "return: 40.00" in prompt and "return: 15.00" not in prompt and "return: 20.00" not in prompt


def test_critic_sees_the_median_rollout_and_statistics() -> None:
    p, codec = _proposer()
    c = _cand(codec, 1, "r2po-search", 30.0)
    ev = p.evidence(c)
    assert ev.returns[0] == pytest.approx(30.0) and ev.returns[2:] == (29.0, 31.0) and ev.episodes == 3
    assert ev.median_return == 30.0 and len(ev.median_rollout) == 50


def test_overflow_is_detected_before_sending() -> None:
    p, codec = _proposer(window=2000)
    p.tell(_cand(codec, 0, "warmup", 10.0))
    p.tell(_cand(codec, 1, "r2po-search", 30.0))
    with pytest.raises(StopSearch, match="context overflow at LLM call 1"):
        p.ask(1)  # chat is None: reaching the LLM would fail differently


def test_overflow_stops_the_run_and_reports_the_best_so_far(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "r"
    # before any answer the prompt size is a local, conservative estimate (one token per two
    # characters): ~2500 characters plus the answer's 104 tokens do not fit 1100, so the run stops
    # before sending anything (the LLM is never started) and reports the best warm-up policy
    code = main(["run", "--env", "CartPole", "--method", "r2po", "--warmup", "4", "--iterations", "6", "--episodes", "3",
                 "--final-episodes", "2", "--context-size", "1100", "--out", str(out), "--quiet"])
    assert code == 0
    capsys.readouterr()
    store = open_store(out)
    status, cands, calls, fe = store.status(), store.candidates(), store.llm_calls(), store.final_eval()
    store.close()
    assert status.startswith("stopped: context overflow at LLM call 0")
    assert len(cands) == 4 and calls == []  # nothing was sent for the overflowing prompt
    assert fe is not None and fe.candidate_index == max(cands, key=lambda c: c.ret).index
    assert json.loads((out / "best_policy.json").read_text())["search"]["candidate"] == fe.candidate_index
    assert main(["resume", str(out), "--quiet"]) == 0  # a stopped run is finished, not continued
    assert len(open_store(out).candidates()) == len(cands)
