"""Helpers shared by tests (importable because pytest puts tests/ on the path)."""

from __future__ import annotations

from ppprops.config import LLMConfig, RunConfig
from ppprops.methods import resolve


def make_config(task: str = "CartPole", method: str = "pp", **kw: object) -> RunConfig:
    llm = kw.pop("llm", LLMConfig())
    # the paper's chat prompt unless a test asks for the document form (tests/test_document_form.py
    # covers that one): these helpers build and read chat messages
    # no selection stage unless a test asks for one (tests/test_study.py covers it): the search alone
    base = dict(warmup=3, iterations=3, top_k=10, episodes=1, final_episodes=3, seed=0, prompt_form="chat", select_top=0)
    base.update(kw)
    return RunConfig(task=task, method=method, mechanisms=resolve(method), llm=llm, **base)  # type: ignore[arg-type]


def doc_block(doc: str, first_line: str) -> str:
    """The code block of a doc page that starts with ``first_line`` (a comment naming the file), up
    to its closing fence: the code exactly as the page shows it."""
    start = doc.index(first_line + "\n")
    return doc[start:doc.index("```", start)]
