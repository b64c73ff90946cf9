"""Token totals (``ppprops.usage``): the sums over the stored calls, by stage; a count the server did not
report is unknown (None), never 0; reasoning tokens are read from the stored answers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ppprops.client.secrets import Secrets
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.summary import format_summary, run_summary
from ppprops.usage import describe, reasoning_tokens, usage

from support import make_config


def _call(attempt: int, prompt: int | None, completion: int | None, reasoning: int | None = None, *, answered: bool = True) -> dict:
    u: dict = {} if prompt is None else {"prompt_tokens": prompt, "completion_tokens": completion}
    if reasoning is not None:
        u["completion_tokens_details"] = {"reasoning_tokens": reasoning}
    body = json.dumps({"choices": [], "usage": u} if u else {"choices": []})
    return {"attempt": attempt, "prompt_tokens": prompt, "completion_tokens": completion, "response": body if answered else None,
            "answered": answered}  # fmt: skip


def test_totals_are_the_sums_over_the_calls_by_stage() -> None:
    calls = [_call(0, 800, 70, 20), _call(1, 810, 60, 5), _call(0, 900, 80, 30), _call(0, 0, 0, answered=False)]
    u = usage(calls)
    assert (u["requests"], u["prompt_tokens"], u["completion_tokens"], u["reasoning_tokens"], u["unknown"]) == (4, 2510, 210, 55, 0)
    assert u["by_stage"]["search"] == {"requests": 3, "prompt_tokens": 1700, "completion_tokens": 150, "reasoning_tokens": 50,
                                       "unknown": 0, "cost_usd": None}  # fmt: skip
    assert u["by_stage"]["corrections"]["prompt_tokens"] == 810 and u["by_stage"]["warmup"]["requests"] == 0
    assert describe(u) == "4 requests, 2,510 prompt + 210 completion tokens (55 reasoning)"


def test_a_server_that_reports_no_usage_is_unknown_not_zero() -> None:
    u = usage([_call(0, 800, 70), _call(0, None, None)])
    assert (u["prompt_tokens"], u["completion_tokens"], u["reasoning_tokens"], u["unknown"]) == (None, None, None, 1)
    assert describe(u) == "2 requests; tokens unknown (1 answers reported no usage)"
    assert reasoning_tokens(None) is None and reasoning_tokens("not json") is None
    assert reasoning_tokens(json.dumps({"usage": {"completion_tokens_details": {"reasoning_tokens": 7}}})) == 7


def test_show_gives_the_run_s_totals(tmp_path: Path) -> None:
    from ppprops.privacy.simulate import EchoOptimizer

    config = make_config("CartPole", "pp", warmup=2, iterations=3, final_episodes=0)
    start(config, tmp_path / "r", llm=EchoOptimizer(config.llm, spread=0.5), secrets=Secrets.generate("u", 10, rng=np.random.default_rng(0)))
    with open_store(tmp_path / "r") as store:
        calls = store.llm_calls()
    s = run_summary(tmp_path / "r")
    expected = usage(calls)
    assert s["usage"] == expected and s["usage"]["requests"] == len(calls) >= 3
    last = format_summary(s).splitlines()[-1]
    assert last.startswith("llm      mean latency ") and last.endswith(f"; {describe(expected)}")


def test_the_cost_is_the_price_times_the_tokens(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from ppprops.cli import main

    calls = [_call(0, 800, 70), _call(1, 200, 30)]
    u = usage(calls, (0.15, 0.60))
    assert u["cost_usd"] == (1000 * 0.15 + 100 * 0.60) / 1e6 and u["by_stage"]["corrections"]["cost_usd"] == (200 * 0.15 + 30 * 0.60) / 1e6
    assert describe(u).endswith(", $0.0002") and usage([_call(0, None, None)], (1.0, 1.0))["cost_usd"] is None
    for bad, line in (("1", "argument --price: expected IN,OUT (dollars per million prompt, completion tokens), got '1'"),
                      ("-1,2", "--price must be two finite numbers >= 0 (dollars per million prompt, completion tokens), got -1,2")):
        try:
            code = main(["run", "--env", "CartPole", "--method", "pp", "--base-url", "http://127.0.0.1:9/v1", "--model", "m",
                         "--price", bad, "--out", str(tmp_path / "r")])  # fmt: skip
        except SystemExit as e:
            code = e.code
        assert code == 2 and capsys.readouterr().err == f"ppprops: error: {line}\n"
        assert not (tmp_path / "r").exists()
