"""Shared fixtures: the real embedded llama.cpp server, started once per session."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture(scope="session")
def embedded_server() -> Iterator[object]:
    from ppprops.llm.embedded import EmbeddedServer

    with EmbeddedServer() as server:
        yield server
