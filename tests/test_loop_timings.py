"""Every candidate records where its time went, which the overhead benchmark relies on."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from ppprops.runner import start
from ppprops.store import open_store

from support import make_config, offline_llm


def test_each_candidate_records_its_ask_and_evaluation_seconds(tmp_path: Path) -> None:
    with offline_llm():
        start(make_config("CartPole", "pp", warmup=4, iterations=4, final_episodes=0), tmp_path / "run")
    store = open_store(tmp_path / "run")
    try:
        times, calls = store.candidate_times(), store.llm_calls()
    finally:
        store.close()
    llm_s: dict[int, float] = defaultdict(float)
    for c in calls:
        llm_s[c["iteration"]] += c["latency_s"]
    assert [t[1] for t in times] == ["warmup"] * 4 + ["llm"] * 4
    created = [t[3] for t in times]
    assert created == sorted(created)
    for (_, source, it, _, ask_s, eval_s), prev, now in zip(times[1:], created[:-1], created[1:], strict=True):
        assert eval_s is not None and ask_s is not None and 0 < eval_s < now - prev + 1e-3
        if source == "llm":  # the ask holds the LLM round trips and fits between two stored candidates
            assert llm_s[it] <= ask_s < now - prev
