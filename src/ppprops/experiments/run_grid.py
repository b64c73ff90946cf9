"""``ppprops experiment``: open the grid, skip what is done, execute the rest, say what happened."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..errors import MissingExtraError
from .grid import DONE, PARTIAL, Grid, Outcome
from .spec import RL, ExperimentSpec

DEFAULT_REMOTE_CONCURRENCY = 4


@dataclass(frozen=True)
class GridResult:
    """What one ``ppprops experiment`` invocation did: an Outcome per run it executed (none for a
    dry run), and how many runs it found done already."""

    root: Path
    outcomes: tuple[Outcome, ...]
    skipped: int  # runs found done before anything was executed

    @property
    def ok(self) -> bool:
        """True when no executed run failed."""
        return all(o.action != "failed" for o in self.outcomes)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def llm_concurrency(spec: ExperimentSpec) -> int | None:
    """The cap on LLM requests in flight: as given; else 4 when any run calls a remote endpoint,
    none when every run has its own embedded server."""
    if spec.execution.llm_concurrency is not None:
        return spec.execution.llm_concurrency
    remote = any(r.kind != RL and r.config.get("llm", {}).get("base_url") for r in spec.runs)
    return DEFAULT_REMOTE_CONCURRENCY if remote else None


def run_grid(
    spec: ExperimentSpec,
    out: Path,
    *,
    ray_address: str | None = None,
    dry_run: bool = False,
    transfer: str = "auto",
    log: Callable[[str], None] = print,
) -> GridResult:
    """Execute every run of ``spec`` in ``out`` that is not done yet.

    Locally (``spec.execution.jobs`` processes, default cores // llm_threads) or on Ray when
    ``ray_address`` is given (see ``execute_ray.run_ray``; ``transfer`` goes there). Progress lines
    (a plan, one per finished run, a closing line) go to ``log``. ``dry_run`` lists every run's
    state and writes nothing. A failed run does not stop the others; it is an Outcome "failed".

    Raises:
        ConfigError: ``out`` is not a grid directory of this spec (see ``Grid.open``), or Ray
            cannot be reached.
        MissingExtraError: the grid has RL runs to execute and the ``rl`` extra is missing, or Ray
            is asked for and not installed.
    """
    threads = spec.execution.llm_threads
    parallel = spec.execution.jobs or max(1, (os.cpu_count() or 1) // threads)
    cap = llm_concurrency(spec)
    grid = Grid(out) if dry_run else Grid.open(out, spec)  # a dry run writes nothing
    states = {r.name: grid.state(r) for r in spec.runs}
    todo = [r for r in spec.runs if states[r.name] != DONE]
    done_before = len(spec.runs) - len(todo)
    where = f"Ray ({ray_address})" if ray_address else f"{parallel} local process(es)"
    log(f"grid {spec.name}: {len(spec.runs)} runs in {grid.root}: {done_before} done, "
        f"{sum(states[r.name] == PARTIAL for r in todo)} to resume, {sum(states[r.name] != PARTIAL for r in todo)} to start; "
        f"{where}, {threads} LLM thread(s) per run" + (f", at most {cap} LLM requests at once" if cap else ""))  # fmt: skip
    for combo in spec.skipped:
        log(f"  not applicable (the paper's '--'): {combo}")
    if dry_run:
        for r in spec.runs:
            log(f"  {states[r.name]:<8} {r.name}")
        return GridResult(grid.root, (), done_before)
    if any(r.kind == RL for r in todo):
        try:
            import stable_baselines3  # noqa: F401
        except ImportError as e:
            raise MissingExtraError("rl", "the [[rl]] runs of this grid") from e
    jobs = [grid.job(r) for r in todo]
    grid.record(executor=where, llm_threads=threads, jobs=parallel, llm_concurrency=cap)
    t0 = time.monotonic()
    count = [done_before]

    def report(o: Outcome) -> None:
        count[0] += 1
        head = f"[{count[0]}/{len(spec.runs)}] {o.name}"
        if o.action == "failed":
            log(f"{head} FAILED after {o.wall_s:.1f} s: {o.error}")
        else:
            log(f"{head} {o.action}, {o.status} in {o.wall_s:.1f} s: best {_fmt(o.best)}, final {_fmt(o.final)}")

    if not jobs:
        outcomes: list[Outcome] = []
    elif ray_address:
        from .execute_ray import run_ray

        outcomes = run_ray(jobs, address=ray_address, grid_id=grid.grid_id, llm_threads=threads, llm_concurrency=cap,
                           transfer=transfer, on_outcome=report)  # fmt: skip
    else:
        from .execute_local import run_local

        outcomes = run_local(jobs, parallel=parallel, llm_threads=threads, llm_concurrency=cap, on_outcome=report)
    failed = [o for o in outcomes if o.action == "failed"]
    log(f"grid {spec.name}: {len(outcomes) - len(failed)} run(s) executed, {done_before} already done, {len(failed)} failed "
        f"in {time.monotonic() - t0:.1f} s" + ("; rerun the same command to retry" if failed else "")
        + f"; tables and plots: ppprops report {out}")  # fmt: skip
    return GridResult(grid.root, tuple(outcomes), done_before)
