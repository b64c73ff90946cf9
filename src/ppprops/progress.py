"""A tqdm progress bar on stderr: iteration, best return so far, last return, LLM latency."""

from __future__ import annotations

from typing import Any

from .runner import RunEvents
from .store import Candidate, FinalEval


class ProgressEvents:
    def __init__(self, *, enabled: bool, label: str) -> None:
        self.enabled = enabled
        self.label = label
        self.bar: Any = None

    def __enter__(self) -> ProgressEvents:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.close()

    def _start(self, done: int, total: int) -> None:
        if self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, desc=self.label, unit="eval", dynamic_ncols=True)

    def _candidate(self, c: Candidate, latency: float | None, best: float) -> None:
        if self.bar is None:
            return
        post = {"it": f"{c.source}:{c.iteration}", "best": f"{best:.1f}", "last": f"{c.ret:.1f}"}
        if latency is not None:
            post["llm"] = f"{latency:.1f}s"
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(1)

    def _final(self, fe: FinalEval) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def hooks(self) -> RunEvents:
        return RunEvents(on_start=self._start, on_candidate=self._candidate, on_final=self._final)
