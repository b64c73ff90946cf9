"""Progress on stderr (tqdm): the search (iteration, best return so far, last return, LLM latency),
the embedded model's start, and the final evaluation's episodes. stdout stays for results."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from .events import RunEvents
from .values import Candidate, FinalEval


class ProgressEvents:
    """``hooks()`` for ``runner.start``/``resume``; no progress is printed when not ``enabled``.

    Nothing is printed before the run's first result (a trial told or failed, the embedded model
    loading, the final evaluation): ``header`` (e.g. the run directory's line), the notices and the
    bar wait for it, so a run refused in its first episode prints its one error line alone.
    """

    def __init__(self, *, enabled: bool, label: str, header: str | None = None) -> None:
        self.enabled = enabled
        self.label = label
        self.bar: Any = None
        self.final_bar: Any = None
        self._held: list[str] = [header] if header is not None and enabled else []
        self._plan: tuple[int, int] | None = None  # (settled, total) from on_start, drawn at the first result
        self._shown = False

    def __enter__(self) -> ProgressEvents:
        return self

    def __exit__(self, *exc: object) -> None:
        for bar in (self.bar, self.final_bar):
            if bar is not None:
                bar.close()
        self.bar = self.final_bar = None

    def _write(self, text: str) -> None:
        if self.enabled:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stderr)

    def _start(self, done: int, total: int) -> None:
        self._plan = (done, total)
        if self.bar is not None:  # the plan changed under a bar already drawn (a stop rule ended the search)
            self.bar.total = total
            self.bar.refresh()

    def _show(self, *, bar: bool = True) -> None:
        """At the first result: the held lines, then the bar (``bar``)."""
        if self._shown:
            return
        self._shown = True
        for line in self._held:
            print(line, file=sys.stderr, flush=True)
        self._held = []
        if bar and self.enabled and self._plan is not None:
            from tqdm import tqdm

            done, total = self._plan
            self.bar = tqdm(total=total, initial=done, desc=self.label, unit="eval", dynamic_ncols=True, file=sys.stderr)

    def _candidate(self, c: Candidate, latency: float | None, best: float) -> None:
        self._show()
        if self.bar is None:
            return
        post = {"it": f"{c.source}:{c.iteration}", "best": f"{best:.1f}", "last": f"{c.ret:.1f}"}
        if latency is not None:
            post["llm"] = f"{latency:.1f}s"
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(1)

    def _llm_loading(self) -> None:
        self._show()
        self._write("loading the embedded model (Gemma 3 270M in a llama.cpp server)...")

    def _llm_ready(self, seconds: float) -> None:
        self._write(f"embedded model ready in {seconds:.1f} s")

    def _final_start(self, episodes: int) -> None:
        self._show(bar=False)
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        if self.enabled:
            from tqdm import tqdm

            self.final_bar = tqdm(total=episodes, desc=f"{self.label} final evaluation", unit="episode", dynamic_ncols=True,
                                  file=sys.stderr)  # fmt: skip

    def _final_episode(self, done: int) -> None:
        if self.final_bar is not None:
            self.final_bar.update(done - self.final_bar.n)

    def _final(self, fe: FinalEval) -> None:
        for bar in (self.bar, self.final_bar):
            if bar is not None:
                bar.close()
        self.bar = self.final_bar = None

    def _notice(self, text: str) -> None:
        """A line the user should read even without progress (``--quiet`` keeps it); held until the first result."""
        if not self._shown:
            self._held.append(f"note: {text}")
        elif self.bar is not None:
            from tqdm import tqdm

            tqdm.write(f"note: {text}", file=sys.stderr)
        else:
            print(f"note: {text}", file=sys.stderr, flush=True)

    def _failed(self, number: int, reason: str) -> None:
        self._show()
        self._notice(f"trial {number} failed: {reason}")
        if self.bar is not None:
            self.bar.update(1)

    def hooks(self) -> RunEvents:
        """The runner's callbacks that drive these progress bars."""
        return RunEvents(on_start=self._start, on_candidate=self._candidate, on_final=self._final,
                         on_llm_loading=self._llm_loading, on_llm_ready=self._llm_ready,
                         on_final_start=self._final_start, on_final_episode=self._final_episode,
                         on_notice=self._notice, on_failed=self._failed)  # fmt: skip


@contextmanager
def episode_events(*, enabled: bool, label: str) -> Iterator[RunEvents]:
    """Hooks that show one bar of episodes (``runner.final_returns``), e.g. for ``policy eval``."""
    progress = ProgressEvents(enabled=enabled, label=label)
    with progress:
        yield RunEvents(on_final_start=lambda n: _episodes_bar(progress, n), on_final_episode=progress._final_episode)


def _episodes_bar(progress: ProgressEvents, episodes: int) -> None:
    if progress.enabled:
        from tqdm import tqdm

        progress.final_bar = tqdm(total=episodes, desc=progress.label, unit="episode", dynamic_ncols=True, file=sys.stderr)
