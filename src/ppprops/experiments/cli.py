"""The ``experiment`` and ``report`` subcommands (parsers here, work in the modules they call)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from ..settings import add_flags, given
from .spec import RESERVED, seeds_flag


def _names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def add_subcommands(sub: Any) -> None:
    """Add ``experiment`` (with every ``run`` flag, overriding the spec) and ``report``."""
    ex = sub.add_parser("experiment", help="run a grid of tasks x methods x seeds (resumable), locally or on Ray")
    ex.add_argument("spec", nargs="?", type=Path, default=None,
                    help="spec file (TOML, or YAML with the experiments extra); see experiments/*.toml")
    ex.add_argument("--out", type=Path, required=True, help="grid directory; rerun the same command to continue it")
    ex.add_argument("--tasks", type=_names, default=None, help="comma list; without a spec: the grid's tasks, with one: keep only these")
    ex.add_argument("--methods", type=_names, default=None,
                    help="comma list of `ppprops run` methods; without a spec: the grid's methods, with one: keep only these")
    ex.add_argument("--seeds", type=seeds_flag, default=None, metavar="N|S1,S2,..",
                    help="seeds 0..N-1, or a list (default: the spec's, else 5)")
    ex.add_argument("--jobs", type=int, default=None, help="runs at once (default: cores // --llm-threads)")
    ex.add_argument("--llm-threads", type=int, default=None,
                    help="threads of each run's embedded model (default 1; results repeat exactly only with the same value)")
    ex.add_argument("--llm-concurrency", type=int, default=None,
                    help="most LLM requests in flight across the grid (default: 4 for a remote endpoint, no cap for the embedded model)")
    where = ex.add_mutually_exclusive_group()
    where.add_argument("--ray-address", default=None, metavar="ADDRESS", help="run on this Ray cluster (e.g. auto, ray://head:10001)")
    where.add_argument("--ray", choices=["local"], default=None, help="start a Ray instance on this machine and run on it")
    ex.add_argument("--dry-run", action="store_true", help="list the runs and their state; run nothing")
    ex.add_argument("--quiet", action="store_true", help="no line per finished run")
    flags = ex.add_argument_group("run settings (any `ppprops run` flag; overrides the spec's [run] tables)")
    add_flags(flags, exclude=RESERVED, groups=None)  # type: ignore[arg-type]

    rp = sub.add_parser("report", help="tables, reward curves, history-cost plots and index.html from a grid directory")
    rp.add_argument("dir", type=Path, help="a grid directory (or any folder of run directories)")
    rp.add_argument("--out", type=Path, default=None, help="where to write (default DIR/report)")


def cmd_experiment(a: argparse.Namespace) -> int:
    """``ppprops experiment``: build the spec (a spec file, or ``--tasks`` and ``--methods``) and run its grid in ``--out``.

    Run flags given on the command line override the spec's ``[run]`` tables; ``--seeds`` replaces
    its seeds (every group's), ``--tasks`` and ``--methods`` keep a subset of its runs. Returns the
    exit code: 0 when no run failed, 1 when one did (rerunning the command retries it), 130 after Ctrl-C.

    Raises:
        ConfigError: no spec and no ``--tasks``/``--methods``, a bad spec or flag, an ``--out`` that
            is not this grid's directory, an unreachable Ray cluster.
        MissingExtraError: YAML spec, Ray or RL runs without their extra.
    """
    from ..errors import ConfigError
    from .run_grid import run_grid
    from .spec import build_spec, flags_table, load_spec

    overrides = given(a)
    execution = {"jobs": a.jobs, "llm_threads": a.llm_threads, "llm_concurrency": a.llm_concurrency}
    if a.spec is not None:
        spec = load_spec(a.spec, overrides=overrides, seeds=a.seeds, only_tasks=a.tasks, only_methods=a.methods, execution=execution)
    else:
        if not a.tasks or not a.methods:
            raise ConfigError("give a spec file, or --tasks and --methods (e.g. --tasks CartPole,Acrobot --methods vanilla,pp)")
        raw = flags_table(a.tasks, a.methods, a.seeds if a.seeds is not None else 5)
        spec = build_spec(raw, source="flags", overrides=overrides, execution=execution)
    ray_address = a.ray_address or a.ray
    try:
        result = run_grid(spec, a.out, ray_address=ray_address, dry_run=a.dry_run,
                          log=(lambda line: None) if a.quiet else (lambda line: print(line, flush=True)))  # fmt: skip
    except KeyboardInterrupt:
        print(f"ppprops: interrupted; rerun the same command to continue the grid in {a.out}", file=sys.stderr)
        return 130
    return 0 if result.ok else 1


def cmd_report(a: argparse.Namespace) -> int:
    """``ppprops report DIR``: write the report (``write_report``), print where ``index.html`` is; returns 0.

    Raises:
        ConfigError: ``DIR`` is not a directory or holds no run.
        MissingExtraError: matplotlib (the ``report`` extra) is not installed.
    """
    from .report import write_report

    t0 = time.monotonic()
    out = write_report(a.dir, a.out)
    print(f"report: {out / 'index.html'} ({time.monotonic() - t0:.1f} s)")
    return 0


__all__ = ["add_subcommands", "cmd_experiment", "cmd_report"]
