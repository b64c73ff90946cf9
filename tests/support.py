"""Helpers shared by tests (importable because pytest puts tests/ on the path)."""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import types
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ppprops.config import LLMConfig, RunConfig
from ppprops.methods import resolve


def make_config(task: str = "CartPole", method: str = "pp", **kw: object) -> RunConfig:
    llm = kw.pop("llm", LLMConfig())
    mechanisms = kw.pop("mechanisms", resolve(method))  # a test may switch a hardening on: resolve(method, pace_requests=True)
    # the paper's chat prompt unless a test asks for the document form (tests/test_document_form.py
    # covers that one): these helpers build and read chat messages
    # no selection stage unless a test asks for one (tests/test_study.py covers it): the search alone
    base = dict(warmup=3, iterations=3, top_k=10, episodes=1, final_episodes=3, seed=0, prompt_form="chat", select_top=0)
    base.update(kw)
    return RunConfig(task=task, method=method, mechanisms=mechanisms, llm=llm, **base)  # type: ignore[arg-type]


def doc_block(doc: str, first_line: str) -> str:
    """The code block of a doc page that starts with ``first_line`` (a comment naming the file), up
    to its closing fence: the code exactly as the page shows it."""
    start = doc.index(first_line + "\n")
    return doc[start:doc.index("```", start)]


@contextmanager
def offline_llm(spread: float = 0.5) -> Iterator[None]:
    """Within the block, every study given no model talks to an ``EchoOptimizer`` (the offline
    stand-in of ``ppprops.privacy.simulate``) instead of its configured endpoint: the test seam
    for command lines (``ppprops.cli.main``), which take no model object."""
    from unittest import mock

    from ppprops.privacy.simulate import EchoOptimizer

    with mock.patch("ppprops.llm.client.connect", lambda llm, **kw: EchoOptimizer(llm, spread=spread)):
        yield


class VirtualClock:
    """Unix seconds that move only when the test says: ``sleep(s)`` (a rig's episode, the pacer's
    wait) adds ``s`` at once, and each reading adds ``TICK`` (as a real clock moves between two
    events: a trial told and the request it lets leave are not at one instant). ``install`` makes it the clock of what a run's request timing is read
    from: the store's stamps (candidates told, requests sent and answered) and the request pacer
    (``Pacer``'s clock and its wait). What the audit then measures is the same on every run of a
    test, whatever the load of the machine: no gap moves with the scheduler.

    Sleeps add up, so two threads that sleep side by side take the sum: a test whose rigs run
    trials at once orders their episodes (``turn``), and ``serial_requests`` sends a round's
    requests one at a time (each paced in turn), so that the order of the stamps is fixed too."""

    TICK = 1e-6  # seconds

    def __init__(self, start: float = 1.8e9) -> None:
        self.now = float(start)
        self._lock = threading.Lock()
        self.turn = threading.Condition()  # rigs that take their episodes in trial order wait on it

    def time(self) -> float:
        """Virtual Unix seconds now."""
        with self._lock:
            self.now += self.TICK
            return self.now

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` pass (at once)."""
        with self._lock:
            self.now += max(0.0, float(seconds))

    def install(self, monkeypatch: Any, *, serial_requests: bool = False) -> None:
        """Make this the clock of the store's stamps and of the request pacer (see the class docstring)."""
        import ppprops.store
        from ppprops.llm import recording
        from ppprops.llm.pacing import Pacer

        stamps = types.SimpleNamespace(**{k: getattr(time, k) for k in dir(time) if not k.startswith("_")})
        stamps.time = self.time  # the store's busy waits keep the real monotonic clock and sleep
        monkeypatch.setattr(ppprops.store, "time", stamps)
        monkeypatch.setitem(Pacer.__init__.__kwdefaults__, "clock", self.time)
        monkeypatch.setitem(Pacer.__init__.__kwdefaults__, "sleep", self.sleep)
        if serial_requests:
            one = threading.Lock()
            send = recording.RecordingLLM.send

            def serial(llm: Any, request: Any, **kw: Any) -> Any:
                with one:
                    return send(llm, request, **kw)

            monkeypatch.setattr(recording.RecordingLLM, "send", serial)


def chat_request(messages: list[dict[str, str]], D: int, *, iteration: int = 0, attempt: int = 0, temperature: float | None = None):  # type: ignore[no-untyped-def]
    """The chat form's request for ``messages`` asking ``D`` numbers (as the chat form builds its requests)."""
    from ppprops.wire.forms import CHAT, CHAT_TEMPERATURE, FormRequest, answer_budget, params_grammar, params_schema

    return FormRequest(CHAT.name, CHAT.endpoint, D, iteration, attempt, messages=tuple(messages),
                       sampling={"temperature": CHAT_TEMPERATURE if temperature is None else temperature}, answer_tokens=answer_budget(D),
                       explains=True, json_schema=params_schema(D), grammar=params_grammar(D))


def document_request(prompt: str, D: int, *, iteration: int = 0, attempt: int = 0, grammar: str | None = None,
                     temperature: float = 0.6, sampling: dict[str, float] | None = None):  # type: ignore[no-untyped-def]
    """The document form's request for ``prompt`` (a document ending inside its open list) asking ``D`` numbers."""
    from ppprops.wire.forms import DOCUMENT, FormRequest, answer_budget

    return FormRequest(DOCUMENT.name, DOCUMENT.endpoint, D, iteration, attempt, prompt=prompt,
                       sampling={"temperature": temperature, **(sampling or {})}, answer_tokens=answer_budget(D, labels=True),
                       grammar=grammar, stop=("]",))


# -- forging a recorded LLM call (the audit must catch what the client would not have sent) ------------------------
Call = dict[str, Any]
Which = int | Call | Callable[[Call], bool]
Edit = dict[str, Any] | Callable[[dict[str, Any]], "dict[str, Any] | None"]
_KEEP: Any = object()


def recorded_calls(run_dir: Path) -> list[Call]:
    """Every recorded LLM call of a run, oldest first: the ``llm_calls`` columns as stored (read with
    plain SQL, not the store), plus ``body``, the request parsed from JSON, and ``decisions`` parsed
    (None where none was recorded)."""
    db = sqlite3.connect(run_dir / "run.sqlite")
    try:
        db.row_factory = sqlite3.Row
        rows = [dict(r) for r in db.execute("SELECT * FROM llm_calls ORDER BY id")]
    finally:
        db.close()
    for r in rows:
        r["body"] = json.loads(r["request"])
        r["decisions"] = json.loads(r["decisions"]) if r.get("decisions") else None
    return rows


def find_call(run_dir: Path, which: Which = -1) -> Call:
    """One recorded call (as ``recorded_calls`` gives it): the ``which``-th in id order (0 the first,
    -1 the last), the first for which ``which(call)`` is true, or, given a call, that call as stored now.

    Raises:
        AssertionError: no call is picked.
    """
    calls = recorded_calls(run_dir)
    if isinstance(which, int):
        assert calls and -len(calls) <= which < len(calls), f"no call {which} of {len(calls)}"
        return calls[which]
    if isinstance(which, dict):
        picked = [c for c in calls if c["id"] == which["id"]]
    else:
        picked = [c for c in calls if which(c)]
    assert picked, "no recorded call of that form"
    return picked[0]


def _edited(old: dict[str, Any], edit: Edit) -> dict[str, Any]:
    if isinstance(edit, dict):
        return edit
    new = edit(old)
    assert new is None or isinstance(new, dict), f"an edit returns the new document or None, not {new!r}"
    return old if new is None else new


def tamper_call(run_dir: Path, which: Which = -1, *, request: Edit | None = None, content: str | None = _KEEP,
                decisions: Edit | None = None) -> int:
    """Forge one recorded LLM call of ``run_dir`` with plain SQL, as if the client had sent (or been
    answered) something else, and return its id. ``which`` picks the call as ``find_call`` does.

    ``request`` is the new request body (a dict), or a function of the recorded body (parsed) that
    returns the new one or edits it in place and returns None; ``decisions`` the same for the
    recorded decisions; ``content`` the new content column (a string, or None). What is not given
    stays as recorded.
    """
    call = find_call(run_dir, which)
    changes: dict[str, Any] = {}
    if request is not None:
        changes["request"] = json.dumps(_edited(call["body"], request))
    if decisions is not None:
        changes["decisions"] = json.dumps(_edited(call["decisions"] or {}, decisions))
    if content is not _KEEP:
        changes["content"] = content
    assert changes, "nothing to change"
    db = sqlite3.connect(run_dir / "run.sqlite")
    try:
        db.execute(f"UPDATE llm_calls SET {', '.join(f'{k} = ?' for k in changes)} WHERE id = ?", (*changes.values(), call["id"]))
        db.commit()
    finally:
        db.close()
    return int(call["id"])
