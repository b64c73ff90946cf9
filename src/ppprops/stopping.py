"""Stopping a search when it is good enough: a target return, a time limit, patience.

``StopRules`` holds the user's rules (``--target-return``, ``--time-limit``, ``--patience``; the
``stop`` group of ``ppprops.search`` / ``create_study``; the same keys in a config file). Each
rule's verdict is data, as pycma's ``stop()`` dictionary is: ``check`` gives one ``StopCheck`` per
rule set, whether it fired and why.

A rule that fires ends the search early, not the run. The study's plan is cut at the next trial
number (``search_end``): the trials already out are still told, then the selection stage and the
final evaluation run as after a full search, and the run's status is ``stopped: <reason>``
(``ppprops show``; ``stop_reason`` in ``show --json``), e.g. ``stopped: target return reached
after 23 candidates``. The rules are checked on this machine, on raw returns, after each told
candidate (the time limit also before each ask); nothing of them is sent.

The clock of ``--time-limit`` is the search's wall time. A process that drives the study
(``ppprops run``, ``resume``, ``Study.optimize``) restarts it where the last one left it, so the
time between two processes is not counted; a study driven by ``ppprops ask`` / ``tell`` counts
from its first ask.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass as plain_dataclass
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import BeforeValidator, Field, model_validator
from pydantic.dataclasses import dataclass

from .errors import ConfigError
from .schema import SCHEMA, Flag, Float, Int, one_line_errors

if TYPE_CHECKING:
    from .seeding import Streams
    from .store import RunStore
    from .values import Candidate

_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
_PART = re.compile(r"(\d+(?:\.\d*)?|\.\d+)([smhd])")


def parse_duration(value: Any) -> float | None:
    """Seconds of a duration: ``90s``, ``20m``, ``2h``, ``1h30m``, ``1.5h``, ``2d``, or a number of
    seconds (an int or float, or its text). None stays None (no limit).

    Raises:
        ValueError: anything else (one line, naming the accepted forms).
    """
    if value is None:
        return None
    if isinstance(value, bool):
        raise ValueError(f"must be a duration such as 90s, 20m or 2h, got {value!r}")
    if isinstance(value, int | float):
        return float(value)
    text = str(value).strip().lower().replace(" ", "")
    try:
        return float(text)
    except ValueError:
        pass
    parts = _PART.findall(text)
    if not parts or "".join(n + u for n, u in parts) != text:
        raise ValueError(f"must be a duration such as 90s, 20m or 2h (or a number of seconds), got {value!r}")
    return sum(float(n) * _UNITS[u] for n, u in parts)


def format_duration(seconds: float) -> str:
    """A duration as ``parse_duration`` reads it back: ``2h``, ``20m``, ``1h30m``, ``90.5s``."""
    whole = round(seconds)
    if abs(seconds - whole) > 1e-9 or whole < 60:
        return f"{seconds:g}s"
    h, rest = divmod(whole, 3600)
    m, s = divmod(rest, 60)
    return "".join(f"{v}{u}" for v, u in ((h, "h"), (m, "m"), (s, "s")) if v)


Duration = Annotated[float | None, BeforeValidator(parse_duration)]


@one_line_errors
@dataclass(frozen=True, config=SCHEMA)
class StopRules:
    """When the search stops before its budget (module docstring); every rule optional.

    Attributes:
        target_return: stop once a search candidate's raw return (its mean over its episodes, in
            the env's reward units) is at least this.
        time_limit_s: stop asking new search candidates once the search has run this many
            seconds of wall time (module docstring: the clock).
        patience: stop after this many search candidates in a row (after the warm-up) whose return
            is not better than the best before them, the warm-up's included.

    Raises:
        ConfigError: on construction, a target that is not finite, a time limit or patience that
            is not positive (one line naming the flag).
    """

    target_return: Annotated[Float | None, Flag(
        "stop the search once a candidate's raw return reaches R (checked on this machine)", metavar="R", default_text="none")] = None
    time_limit_s: Annotated[Duration, Flag(
        "stop asking new search candidates after this much wall time of the search: 90s, 20m, 2h, 1h30m (or seconds)",
        name="time-limit", metavar="DURATION", default_text="none")] = None
    patience: Annotated[Int | None, Field(ge=1), Flag(
        "stop after N search candidates in a row without a better return than the best before them (the warm-up's included)",
        metavar="N", default_text="none")] = None

    @model_validator(mode="after")
    def _finite(self) -> StopRules:
        if self.target_return is not None and not math.isfinite(self.target_return):
            raise ConfigError(f"--target-return must be a finite number, got {self.target_return}")
        if self.time_limit_s is not None and not (math.isfinite(self.time_limit_s) and self.time_limit_s > 0):
            raise ConfigError(f"--time-limit must be a positive duration such as 90s, 20m or 2h, got {self.time_limit_s:g} seconds")
        return self

    @property
    def given(self) -> bool:
        """True when any rule is set."""
        return self.target_return is not None or self.time_limit_s is not None or self.patience is not None


@plain_dataclass(frozen=True)
class StopCheck:
    """One rule's verdict: ``rule`` (``target_return``, ``time_limit``, ``patience``), whether it
    ``fired``, and ``why`` (one line: what was measured against what)."""

    rule: str
    fired: bool
    why: str


def check(rules: StopRules, candidates: Sequence[Candidate], *, elapsed_s: float | None) -> list[StopCheck]:
    """The verdict of every rule set, in the order target, time limit, patience.

    ``candidates``: the told candidates (re-evaluations of the selection stage are left out;
    patience counts those after the warm-up's); ``elapsed_s``: the search's clock (None: the time
    limit is not checked now).
    """
    search = sorted((c for c in candidates if c.reevaluates is None), key=lambda c: c.index)
    out: list[StopCheck] = []
    if rules.target_return is not None:
        hit = next((c for c in search if math.isfinite(c.ret) and c.ret >= rules.target_return), None)
        out.append(StopCheck("target_return", hit is not None,
                             f"candidate {hit.index}'s return {hit.ret:.6g} reached the target {rules.target_return:g}" if hit is not None
                             else f"no return reached the target {rules.target_return:g}"))  # fmt: skip
    if rules.time_limit_s is not None and elapsed_s is not None:
        limit = format_duration(rules.time_limit_s)
        out.append(StopCheck("time_limit", elapsed_s >= rules.time_limit_s,
                             f"the search's clock is at {format_duration(round(elapsed_s, 1))} (time limit {limit})"))
    if rules.patience is not None:
        best, streak = -math.inf, 0
        for c in search:
            ret = c.ret if math.isfinite(c.ret) else -math.inf
            if c.source not in ("warmup", "init"):  # the warm-up's draws and the given policies
                streak = 0 if ret > best else streak + 1
            best = max(best, ret)
        out.append(StopCheck("patience", streak >= rules.patience,
                             f"{streak} candidates in a row without a better return (patience {rules.patience})"))
    return out


TARGET_DELAY = 8  # under a hardening, a reached target ends the search 0 to 7 candidates later (a keyed draw)

_REASONS = {"target_return": "target return reached", "time_limit": "time limit {limit} reached",
            "patience": "patience of {patience} candidates without a better return spent"}  # fmt: skip


def reason(rules: StopRules, fired: StopCheck, candidates: int) -> str:
    """The run's stop reason for a fired rule, after ``candidates`` told search candidates."""
    limit = format_duration(rules.time_limit_s) if rules.time_limit_s is not None else ""
    return f"{_REASONS[fired.rule].format(limit=limit, patience=rules.patience)} after {candidates} candidate{'s' * (candidates != 1)}"


# -- the study's stop state (RunStore.stop_state) ------------------------------------------------------
def search_end(store: RunStore) -> int | None:
    """The trial number where the search ended early (the selection stage starts there), or None."""
    end = store.stop_state().get("end")
    return None if end is None else int(end)


def stages(store: RunStore) -> list[tuple[int, int]]:
    """(first trial number, trials) of each selection stage after which the search went on
    (``continue_search``), oldest first; [] for a search never continued."""
    return [(int(first), int(top)) for first, top in store.stop_state().get("stages", [])]


def planned_end(store: RunStore, warmup: int, iterations: int) -> int:
    """The trial number where the search ends when it runs its budget: the warm-up, the iterations
    and the trials of the selection stages it went on after (``stages``)."""
    return warmup + iterations + sum(top for _, top in stages(store))


def continue_search(store: RunStore, rules: StopRules, *, warmup: int, iterations: int, old_iterations: int,
                    stopped: str | None) -> tuple[str, dict[str, Any]] | None:  # fmt: skip
    """What the limits a ``resume`` gives (``rules``, the search's ``iterations``, which were
    ``old_iterations``) do to a run; nothing is written here. When its search ended (its budget
    spent, or a stop rule) and the limits leave room, the search goes on after the selection stage
    it ran (whose trials stay: ``stages``): returns a note line and the stop state to store
    (``RunStore.set_stop_state``). For a search that did not end there is nothing to do (None):
    the new limits apply as it goes.

    ``stopped``: the reason of a run stopped on purpose (its stored status), else None.

    Raises:
        ConfigError: the limits do not let the search go on (its budget is spent, a rule fires at
            once, or it stopped for a reason no limit lifts), or ``iterations`` is below what it
            already asked; nothing is changed then.
    """
    state, past = store.stop_state(), stages(store)
    past_trials = sum(top for _, top in past)
    n = store.next_number()
    if state.get("end") is None and stopped:
        raise ConfigError(f"the run stopped: {stopped}; new limits do not lift that (only a search ended by its budget or a stop rule "
                          "goes on)")  # fmt: skip
    budget_end = warmup + old_iterations + past_trials
    end = int(state["end"]) if state.get("end") is not None else budget_end if n >= budget_end else None
    searched = (end if end is not None else n) - past_trials - warmup  # search candidates asked (warm-up's not counted)
    if iterations < searched:
        raise ConfigError(f"--iterations {iterations} is fewer than the {searched} search candidates already asked")
    if end is None:
        return None
    if end >= warmup + iterations + past_trials:
        raise ConfigError(f"the search ran its whole budget (--warmup {warmup}, --iterations {end - past_trials - warmup}): give a larger "
                          "--iterations to go on")  # fmt: skip
    fired = next((c for c in check(rules, store.candidates(), elapsed_s=float(state.get("spent", 0.0))) if c.fired), None)
    if fired is not None:
        raise ConfigError(f"the search would stop again at once: {fired.why}; give a larger limit to go on")
    done = n - end  # the selection stage's trials asked after the search ended
    kept = {k: v for k, v in state.items() if k not in ("end", "rule", "why", "reason")}
    why = f" (it had stopped: {state['reason']})" if state.get("reason") else ""
    return (f"the search goes on after its {end - past_trials} candidates{why}",
            {**kept, "stages": [*map(list, past), *([[end, done]] if done else [])]})


def keyed_delay(streams: Streams, store: RunStore) -> int:
    """The candidates a reached target still runs under a hardening: uniform in [0,
    ``TARGET_DELAY``), from a stream keyed by the secrets (one draw per stop of the run)."""
    from .seeding import STOP

    return int(streams.rng(STOP, len(stages(store))).integers(0, TARGET_DELAY))


def stop_reason(store: RunStore) -> str | None:
    """Why the search ended early (``reason``), or None when it did not."""
    return store.stop_state().get("reason")


def restart_clock(store: RunStore, rules: StopRules, now: float) -> None:
    """A process starts driving the study at ``now`` (Unix seconds): the clock goes on from the
    time already spent, leaving out the time since the last check."""
    if rules.time_limit_s is None:
        return
    state = store.stop_state()
    store.set_stop_state({**state, "spent": float(state.get("spent", 0.0)), "at": now})


def _tick(store: RunStore, state: dict[str, Any], now: float) -> float:
    """The clock at ``now``, stored: the time spent plus the time since the last check (none before the first)."""
    spent = float(state.get("spent", 0.0)) + (max(0.0, now - float(state["at"])) if "at" in state else 0.0)
    state.update(spent=spent, at=now)
    return spent


def update(store: RunStore, rules: StopRules, *, planned_end: int, now: float, told: bool,
           delay: Callable[[], int] | None = None) -> str | None:  # fmt: skip
    """Check the rules (after a tell: ``told``; else before an ask, the time limit only) and, when
    one fires before the search's budget is spent, cut the search at the next trial number and
    store why. Returns the stop reason when the search ended now, else None.

    ``planned_end``: the trial number where the search would end (``planned_end``); ``now``:
    Unix seconds; ``delay``: under a hardening, a keyed draw in [0, ``TARGET_DELAY``) of the
    candidates a reached target still runs, so that the end of the requests does not mark the
    candidate that reached it (docs/threat-model.md, "Stopping early"). Nothing is read or written
    when no rule is set.
    """
    if not rules.given:
        return None
    state = store.stop_state()
    if state.get("end") is not None:
        return None
    elapsed = _tick(store, state, now) if rules.time_limit_s is not None else None
    by_returns = told and (rules.target_return is not None or rules.patience is not None)
    candidates = store.candidates() if by_returns else []  # the time limit alone reads none
    rules_now = rules if by_returns else StopRules(time_limit_s=rules.time_limit_s)
    fired = next((c for c in check(rules_now, candidates, elapsed_s=elapsed) if c.fired), None)
    end = store.next_number()
    if fired is not None and fired.rule == "target_return" and delay is not None:
        end = min(end + delay(), planned_end)
    if fired is not None and end < planned_end:
        told_search = sum(1 for c in (candidates or store.candidates()) if c.reevaluates is None)
        more = end - store.next_number()
        state.update(end=end, rule=fired.rule, why=fired.why, reason=reason(rules, fired, told_search)
                     + (f" (and {more} more, a keyed delay)" if more else ""))
    if elapsed is not None or "end" in state:
        store.set_stop_state(state)
    return state.get("reason") if "end" in state else None


__all__ = ["Duration", "StopCheck", "StopRules", "check", "continue_search", "format_duration", "keyed_delay", "parse_duration", "planned_end", "reason",
           "restart_clock", "search_end", "stages", "stop_reason", "update"]
