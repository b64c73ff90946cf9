"""Request pacing: the provider's clock should not follow the client's evaluation time.

What a provider sees besides the request bodies is when each request arrives. The gap between
its answer and the next request is the client's own time: evaluating the candidate it proposed
(on a rig that runs in real time, proportional to the episode's steps, hence to the CartPole
return) and proposing the next. ``Pacer`` pads that gap: a new request (a request's first try;
retries are not held) waits until the gap reaches

    pad = headroom x max(every gap seen so far in the run, the longest time between two
          warm-up trials)

plus a jitter drawn uniformly in [0, jitter x pad] from a stream keyed by the run's secrets
(``seeding.PACING``). Every gap shorter than the pad leaves at pad + jitter, whatever the
evaluation took; a gap longer than the pad leaves as it is and raises the pad (with ``headroom``
2, that happens only when the client's time more than doubles the longest seen: a few times per
run at most, each telling the provider "longer than ever"). A gap longer than ``PAUSE`` pads is
a pause, not an evaluation (a robot taken off-line, a process restarted by ``resume``, the night
between two sessions of a shell loop): it leaves as it is and leaves the pad alone, so one pause
does not slow every later request to twice its length. A driving loop that starts
(``Study.optimize``: ``run``, ``resume``) starts the clock afresh with ``restart``: its first
request leaves at once, as a run's first does. The state (the last answer's time, the longest
gap, the number of requests paced) is kept in the store, so processes that drive one study in
turn (``ppprops ask``) pace as one. Cost: each request waits pad + jitter - gap; ``benchmarks/``
measures it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

HEADROOM = 2.0
JITTER = 0.25
PAUSE = 10.0  # a gap of more than PAUSE pads is a pause: unpadded, and the pad stays


class PacingState(Protocol):
    """Where the pacer keeps its state (``store.RunStore``)."""

    def pacing_state(self) -> dict[str, Any]:
        """The state saved last ({} at first)."""
        ...

    def set_pacing_state(self, state: Mapping[str, Any]) -> None:
        """Save the state."""
        ...


class Pacer:
    """Pads the gap before each new request (see the module docstring).

    Args:
        state: the store (``pacing_state``/``set_pacing_state``).
        rng: the keyed generator of draw ``n`` (``seeding.Streams.rng(seeding.PACING, n)``).
        floor: seconds the pad never goes below, computed when first needed (the study: the
            longest time between two warm-up trials).
        headroom, jitter: as in the module docstring (dimensionless).
        clock, sleep: Unix seconds now, and how to wait (tests replace them).
    """

    def __init__(self, state: PacingState, rng: Callable[[int], np.random.Generator], *, floor: Callable[[], float] = lambda: 0.0,
                 headroom: float = HEADROOM, jitter: float = JITTER, clock: Callable[[], float] = time.time,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.state, self.rng, self.floor = state, rng, floor
        self.headroom, self.jitter = float(headroom), float(jitter)
        self.clock, self.sleep = clock, sleep
        self._lock = threading.Lock()
        self.waited_s = 0.0  # seconds this process waited

    def before_request(self) -> float:
        """Wait until the gap since the last answer reaches the pad plus its keyed jitter; returns the seconds waited."""
        with self._lock:
            st = self.state.pacing_state()
            last = st.get("last_answer")
            n = int(st.get("requests", 0))
            if last is None:
                self.state.set_pacing_state({**st, "requests": n + 1})
                return 0.0
            gap = max(0.0, self.clock() - float(last))
            longest = max(float(st.get("longest_gap", 0.0)), float(self.floor()))
            pad = self.headroom * longest
            paused = pad > 0 and gap > PAUSE * pad
            target = gap if paused else max(gap, pad) + self.jitter * pad * float(self.rng(n).uniform())
            self.state.set_pacing_state({**st, "longest_gap": longest if paused else max(longest, gap), "requests": n + 1})
        wait = target - gap
        if wait > 0:
            self.sleep(wait)
            self.waited_s += wait
        return max(wait, 0.0)

    def restart(self) -> None:
        """Forget the last answer's time: a driving loop starts, and its first request leaves at once
        (the time since a previous process's last answer is a pause, not an evaluation)."""
        with self._lock:
            st = self.state.pacing_state()
            if st.get("last_answer") is not None:
                self.state.set_pacing_state({k: v for k, v in st.items() if k != "last_answer"})

    def answered(self) -> None:
        """Note that an answer (or a request's final failure) came back now."""
        with self._lock:
            self.state.set_pacing_state({**self.state.pacing_state(), "last_answer": self.clock()})
