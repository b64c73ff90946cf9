"""Helpers shared by tests (importable because pytest puts tests/ on the path)."""

from __future__ import annotations

from ppprops.config import LLMConfig, RunConfig
from ppprops.methods import resolve


def make_config(task: str = "CartPole", method: str = "pp", **kw: object) -> RunConfig:
    llm = kw.pop("llm", LLMConfig())
    base = dict(warmup=3, iterations=3, top_k=10, episodes=1, final_episodes=3, seed=0)
    base.update(kw)
    return RunConfig(task=task, method=method, mechanisms=resolve(method), llm=llm, **base)  # type: ignore[arg-type]
