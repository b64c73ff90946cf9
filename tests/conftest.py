"""Shared fixtures: the real embedded llama.cpp server, started once per session. And the suite's
Hypothesis profile: the same examples on every run (``derandomize``: drawn from a seed each test's
own code gives; no example database carried from an earlier run) and no deadline per example (a
loaded machine takes longer, not wrongly), so that a property test fails on a bug, not by chance.
``HYPOTHESIS_PROFILE=explore`` draws fresh examples (1000 where a test sets no number) to look for new failures."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from hypothesis import settings

settings.register_profile("ppprops", derandomize=True, deadline=None, database=None, print_blob=True)
settings.register_profile("explore", deadline=None, max_examples=1000, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ppprops"))


@pytest.fixture(scope="session")
def embedded_server() -> Iterator[object]:
    from ppprops.llm.embedded import EmbeddedServer

    with EmbeddedServer() as server:
        yield server
