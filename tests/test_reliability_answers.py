"""Bad answers and an endpoint that stays down, through a real run against the fault server:
each kind is classified, counted and shown; `stop` leaves a resumable run, `skip` goes on."""

from __future__ import annotations

import json
import sqlite3
from collections import Counter
from pathlib import Path

import pytest

from ppprops.cli import main
from ppprops.config import LLMConfig
from ppprops.errors import LLMError
from ppprops.runner import resume, start
from ppprops.store import open_store
from ppprops.summary import run_summary
from ppprops.testing.fault_server import ANSWER_KINDS, FaultConfig, FaultServer

from support import make_config

# what the client-side parser calls each injected bad answer (None: usable after all)
PARSED_AS = {
    "empty": "empty", "truncated": "truncated", "wrong_length": "wrong_length", "nan": "non_finite", "inf": "non_finite",
    "prose": "no_numbers", "several_vectors": "several_vectors", "refusal": "refusal", "huge": None, "reasoning_only": None,
}


def _llm(server: FaultServer, **kw: object) -> LLMConfig:
    settings: dict[str, object] = dict(
        structured="json_schema", timeout_s=1.0, transport_retries=1, retry_base_s=0.01, retry_max_s=0.02
    )
    settings.update(kw)
    return LLMConfig(base_url=server.base_url, model="fault", **settings)  # type: ignore[arg-type]


@pytest.mark.parametrize("kind", ANSWER_KINDS)
def test_each_bad_answer_kind_is_classified_and_recorded(tmp_path: Path, kind: str) -> None:
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=(kind,), seed=1)) as server:
        start(make_config(warmup=2, iterations=1, final_episodes=0, parse_retries=0, llm=_llm(server)), tmp_path / "r")
    store = open_store(tmp_path / "r")
    cand = store.candidates()[2]
    (call,) = store.llm_calls()
    store.close()
    expected = PARSED_AS[kind]
    assert call["ok"] and call["parse_error"] == expected
    if expected is not None:
        assert cand.source == "fallback" and cand.note == f"after {expected}"
    elif kind == "huge":  # accepted, then clipped into the box (1e308 would decode to inf)
        assert cand.source == "llm" and cand.clipped >= 1 and max(abs(cand.params)) <= 6.0
    else:  # reasoning_only: empty content, the vector taken from the reasoning text, and marked so
        assert call["content"] == "" and call["answer_source"] == "reasoning"
        assert cand.source == "llm" and "reasoning" in cand.note


def test_answer_failures_are_counted_per_kind_in_show_json(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "r"
    with FaultServer(FaultConfig(fault_rate=0.7, kinds=ANSWER_KINDS, seed=4)) as server:
        start(make_config(warmup=3, iterations=25, final_episodes=0, parse_retries=1, llm=_llm(server)), out)
        injected = server.stats()["injected"]
    expected = Counter()
    for kind, n in injected.items():
        if PARSED_AS[kind]:
            expected[PARSED_AS[kind]] += n
    assert main(["show", str(out), "--json"]) == 0
    counts = json.loads(capsys.readouterr().out)["counts"]
    assert counts["answer_failures"] == dict(expected) and sum(expected.values()) > 5
    assert counts["answers_from_reasoning"] == injected.get("reasoning_only", 0)
    assert counts["candidates"] == 28 and counts["transport_failures"] == {}
    assert main(["show", str(out)]) == 0
    assert "answers  unusable: " in capsys.readouterr().out


def test_endpoint_down_stops_resumably_then_resumes(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "r"
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("http_503",))) as server:
        with pytest.raises(LLMError, match="ppprops resume"):
            start(make_config(warmup=3, iterations=2, final_episodes=0, llm=_llm(server, transport_retries=2)), out)
        s = run_summary(out)
        assert s["status"].startswith("failed: LLM endpoint failed 3 times in a row") and s["counts"]["candidates"] == 3
        assert s["counts"]["transport_failures"] == {"http_503": 3} and s["counts"]["retries"] == 2
        assert [c["retry"] for c in s["llm_calls"]] == [0, 1, 2] and not any(c["ok"] for c in s["llm_calls"])

        code = main(["resume", str(out), "--quiet"])  # the CLI: one line, exit 2, still resumable
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "failed 3 times in a row" in err and f"ppprops resume {out}" in err

        server.config.fault_rate = 0.0  # the endpoint recovers
        resume(out)
    s = run_summary(out)
    assert s["status"] == "finished" and s["counts"]["candidates"] == 5 and s["counts"]["llm"] == 2
    with sqlite3.connect(out / "run.sqlite") as con:
        assert con.execute("SELECT COUNT(*), COUNT(DISTINCT idx) FROM candidates").fetchone() == (5, 5)


def test_endpoint_down_with_skip_records_fallbacks_and_goes_on(tmp_path: Path) -> None:
    out = tmp_path / "r"
    with FaultServer(FaultConfig(fault_rate=1.0, kinds=("reset",))) as server:
        start(make_config(warmup=3, iterations=3, final_episodes=0, on_llm_failure="skip", llm=_llm(server)), out)
    s = run_summary(out)
    c = s["counts"]
    assert s["status"] == "finished" and c["fallback"] == 3 and c["llm_unavailable"] == 3
    assert c["fallback_reasons"] == {"llm_unavailable": 3} and c["transport_failures"] == {"dropped": 6}
    assert all(x["note"] == "after llm_unavailable (dropped)" for x in s["candidates"][3:])
