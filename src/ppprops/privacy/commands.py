"""The ``audit`` and ``privacy-report`` subcommands, and the one-line audit printed after a run.

Kept here so the main CLI only registers them; errors are ``PPPropsError``s, which the main CLI
turns into one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import ConfigError

if TYPE_CHECKING:
    from ..tasks.base import Task
    from .simfit import SimLimits


def add_privacy_commands(sub: argparse._SubParsersAction, parser_class: type[argparse.ArgumentParser]) -> None:  # type: ignore[type-arg]
    """Add the ``audit`` and ``privacy-report`` parsers to the main CLI's subparsers ``sub``.

    ``parser_class`` is accepted for the main CLI's calling convention and not used here.
    """
    au = sub.add_parser("audit", help="check every recorded request of a run or study for raw values (exit 0 clean; 1 leak, unverified or exposed)")
    au.add_argument("dir", type=Path, help="a run or study directory")
    au.add_argument("--strict", action="store_true", help="also fail (exit 1) on known side channels")
    au.add_argument("--json", action="store_true", help="one JSON object with every finding on stdout")
    _sim_options(au)

    pr = sub.add_parser("privacy-report", help="attacks x scheme (pp, pp-hardened) and their search results")
    pr.add_argument("--runs", type=Path, default=None, metavar="DIR",
                    help="analyse the run directories under DIR instead of starting new runs")
    pr.add_argument("--envs", default=None,
                    help="tasks for new runs, comma-separated (default CartPole,Acrobot; none with --task-file alone)")
    pr.add_argument("--task-file", type=Path, action="append", default=[], metavar="FILE",
                    help="a task file for new runs, e.g. your own robot's (repeatable; with --envs, both)")
    pr.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 for new runs (default 5)")
    pr.add_argument("--warmup", type=int, default=10, help="warm-up policies per new run (default 10)")
    pr.add_argument("--iterations", type=int, default=10,
                    help="LLM iterations per new run (default 10: short runs; 0: warm-up only, to compare the warm-ups)")
    pr.add_argument("--final-episodes", type=int, default=20, help="fresh episodes for each new run's best policy (default 20)")
    pr.add_argument("--out", type=Path, default=None, help="where new runs and the report go (default runs/privacy-report-<time>)")
    pr.add_argument("--offline", action="store_true",
                    help="new runs talk to an offline stand-in optimizer instead of the embedded model (fast; for many draws)")
    pr.add_argument("--pace-requests", action="store_true",
                    help="new runs pace their LLM requests (the pace_requests switch, both schemes): the timing channel closed")
    pr.add_argument("--number-format", choices=("decimal", "grid"), default=None,
                    help="how new runs write encoded parameters (both schemes; default: the run default, decimal)")
    pr.add_argument("--json", action="store_true", help="print one JSON list of per-run analyses")
    _sim_options(pr)


def _sim_options(p: argparse.ArgumentParser) -> None:
    from .simfit import DEFAULT_LIMITS

    d = DEFAULT_LIMITS
    p.add_argument("--sim-steps", type=int, default=d.vector_steps, metavar="N",
                   help=f"simulated steps each simulator attack may use with a vectorised simulator (default {d.vector_steps:.3g}; "
                        f"the real env gets N/{d.vector_steps // d.env_steps})")
    p.add_argument("--sim-seconds", type=float, default=d.seconds, metavar="S",
                   help="optional wall-clock cap of each simulator attack, in seconds (default: none; with a cap the "
                        "result can depend on the machine's load)")
    p.add_argument("--no-simulate", action="store_true", help="skip the simulator attacks (listed as not run)")


def _limits(a: argparse.Namespace) -> SimLimits:
    from .simfit import DEFAULT_LIMITS, SimLimits

    if a.sim_steps < 1 or (a.sim_seconds is not None and not a.sim_seconds > 0):
        raise ConfigError("--sim-steps must be >= 1 and --sim-seconds > 0")
    ratio = DEFAULT_LIMITS.vector_steps // DEFAULT_LIMITS.env_steps
    return SimLimits(vector_steps=a.sim_steps, env_steps=max(1, a.sim_steps // ratio), seconds=a.sim_seconds)


def cmd_audit(a: argparse.Namespace) -> int:
    """``ppprops audit DIR``: print the audit (text, or one JSON object with ``--json``); returns its exit code.

    0 when nothing leaked, nothing is unverified and no secret is exposed (with ``--strict``: and
    no known channel either), else 1.

    Raises:
        StoreError: ``DIR`` is not a prompted search run directory, or its store cannot be read.
    """
    from .audit import audit_run

    report = audit_run(a.dir, limits=_limits(a), simulate=not a.no_simulate)
    print(json.dumps(report.to_json(a.strict)) if a.json else report.format(a.strict))
    return report.exit_code(a.strict)


def cmd_privacy_report(a: argparse.Namespace) -> int:
    """``ppprops privacy-report``: analyse the runs under ``--runs``, or start the matrix of new runs
    (tasks x schemes pp, pp-hardened x seeds) first; print the report, write it next to the runs. Returns 0.

    Raises:
        ConfigError: no run with its key file under ``--runs``, bad counts, an unfinished run in
            the way of a new one.
        UnknownTaskError: an ``--envs`` name that names no task.
        TaskFileError: a ``--task-file`` that cannot be read or declares a bad task.
        StoreError, KeyFileError: a run directory or key file that cannot be read.
        LLMError: the embedded model could not serve a new run.
    """
    from ..rundir import DB_NAME, KEY_NAME, find_runs
    from .matrix import privacy_report, run_matrix, write_report

    if a.runs is not None and (a.pace_requests or a.number_format):
        flag = "--pace-requests" if a.pace_requests else "--number-format"
        raise ConfigError(f"{flag} is a setting of new runs; the runs under --runs were made as they were")
    if a.runs is not None:
        dirs = find_runs(a.runs, recursive=True, with_key=True)
        if not dirs:
            raise ConfigError(f"no run directories (with {DB_NAME} and {KEY_NAME}) under {a.runs}")
        out = a.runs
    else:
        if a.seeds < 1 or a.warmup < 1 or a.iterations < 0:
            raise ConfigError("--seeds and --warmup must be >= 1, --iterations >= 0 (0: warm-up only, no LLM)")
        from ..tasks import get_task, load_task

        names = "CartPole,Acrobot" if a.envs is None and not a.task_file else a.envs or ""
        envs: list[str | Task] = [get_task(e.strip()) for e in names.split(",") if e.strip()]
        envs += [load_task(None, task_file=f) for f in a.task_file]
        if not envs:
            raise ConfigError("--envs names no task (give task names, or --task-file FILE)")
        out = a.out or Path("runs") / f"privacy-report-{time.strftime('%Y%m%d-%H%M%S')}"
        dirs = run_matrix(out, envs=envs, seeds=range(a.seeds), warmup=a.warmup, iterations=a.iterations,
                          final_episodes=a.final_episodes, log=lambda s: print(s, file=sys.stderr), offline=a.offline,
                          settings={**({"pace_requests": True} if a.pace_requests else {}),
                                    **({"number_format": a.number_format} if a.number_format else {})})
    text, analyses = privacy_report(dirs, _limits(a), log=lambda s: print(s, file=sys.stderr), simulate=not a.no_simulate)
    write_report(out, text, analyses, "ppprops " + " ".join(shlex.quote(x) for x in sys.argv[1:]))
    print(json.dumps([x.to_json() for x in analyses]) if a.json else text)
    if not a.json:
        print(f"\nreport written to {Path(out) / 'privacy-report.md'}")
    return 0


PRIVACY_HANDLERS: dict[str, Callable[[argparse.Namespace], int]] = {"audit": cmd_audit, "privacy-report": cmd_privacy_report}


AUDIT_MODES = ("quick", "full", "off")  # ``run --audit`` / ``resume --audit``: the audit a finished run prints about itself


def self_audit_line(run_dir: Path, mode: str = "quick") -> str:
    """The verdict a finished run prints about its own transcript (never any value, never the key).

    ``quick`` (the default): the transcript checks of ``audit_run(attacks=False)``: every request
    read and accounted for, no raw value in it; the line says the attacks did not run and names
    ``ppprops audit DIR``, and under a preset that keeps the paper's channels, that the full audit
    usually finds the run EXPOSED by design. ``full``: every attack too, as ``ppprops audit DIR``
    runs them (same limits, same verdict). ``off``: no audit, only the command that runs it.
    """
    from .audit import audit_run

    if mode not in AUDIT_MODES:
        raise ValueError(f"audit mode {mode!r} is not one of {', '.join(AUDIT_MODES)}")
    how = f"'ppprops audit {run_dir}' runs them"
    if mode == "off":
        return f"privacy audit: not run (--audit off): 'ppprops audit {run_dir}' checks the transcript and runs the attacks on it"
    full = mode == "full"
    try:
        report = audit_run(run_dir, attacks=full)
    except Exception as e:  # the run itself succeeded; a failing check must not turn that into an error
        return f"privacy audit: could not check this run ({e.__class__.__name__}: {e}); try ppprops audit {run_dir}"
    if report.requests == 0:
        return "privacy audit: no LLM request was sent"
    kinds = sorted({f.kind for f in report.channels})
    channels = f" Known channels: {', '.join(kinds)}." if kinds else ""
    if full:
        verdict = report.verdict().rstrip(".")  # an EXPOSED verdict ends with its own sentence
        return f"privacy audit: {verdict}.{channels} Details: ppprops audit {run_dir}"
    checked = f"quick check of {report.requests} request{'s' if report.requests != 1 else ''}"
    if not report.clean:  # a leak, an identifier or something unaccounted for: the attacks cannot make it better
        return f"privacy audit: {report.verdict()} ({checked}).{channels} The attacks on the transcript did not run: {how}."
    known = f"; known channels: {', '.join(kinds)}" if kinds else ""
    head = f"privacy audit: nothing raw was sent ({checked}{known}). Attacks not run: 'ppprops audit {run_dir}'"
    if _keeps_paper_channels(report.mechanisms):
        return f"{head}; they usually find {report.method} EXPOSED by design (pp-hardened closes its channels)."
    return f"{head}."


def _keeps_paper_channels(mechanisms: dict[str, bool]) -> bool:
    """The preset hides something and closes none of the channels the paper's scheme keeps (no hardening switch)."""
    from ..client.mechanisms import HARDENING

    hides = mechanisms.get("encode_params", False) or mechanisms.get("scale_rewards", False)
    return bool(hides) and not any(mechanisms.get(k, False) for k in HARDENING)
