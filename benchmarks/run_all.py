"""The benchmark suite: every figure of benchmarks/RESULTS.md, measured in one run.

    python benchmarks/run_all.py                 # about 2 hours on 2 idle cores; rewrites benchmarks/RESULTS.md
    python benchmarks/run_all.py --quick --results /tmp/RESULTS.md   # tiny budgets: checks the suite runs

Needs the ``baselines`` and ``mujoco`` extras (CMA-ES; Ant and Humanoid). Runs are kept under
``--out`` (default benchmarks/out), so every figure can be traced back to a run store
(``ppprops show``, ``ppprops audit``). Benchmarks run one after another, never side by side,
except the quality grid, which uses both cores on purpose. Ratios compare things measured in this
same run; absolute times depend on the machine and its load, which the header records.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

import bench_cache
import bench_eval
import bench_history
import bench_overhead
import bench_prompt
import bench_quality
import bench_readme
from _common import Context, Section, machine, table

# Order matters: later benchmarks replay runs that earlier ones recorded (see Context.cache).
SUITE = (("quality", bench_quality), ("prompt", bench_prompt), ("history", bench_history), ("cache", bench_cache),
         ("overhead", bench_overhead), ("eval", bench_eval), ("readme", bench_readme))
HERE = Path(__file__).resolve().parent


def render(sections: list[Section], *, started: str, host: str, command: str, total_s: float, quick: bool) -> str:
    head = [
        "# Benchmark results",
        "",
        "Written by `python benchmarks/run_all.py`; do not edit by hand, rerun it.",
        "",
        f"- Date: {started}",
        f"- Machine: {host}",
        f"- Command: `{command}`",
        f"- Wall time of the whole suite: {total_s / 60:.1f} min",
    ]
    if quick:
        head += ["", "**Quick mode: tiny budgets that only check the suite runs. These figures mean nothing.**"]
    rows = [[s.title.split(". ", 1)[0], t, m, {True: "met", False: "**not met**", None: "(no target)"}[ok]]
            for s in sections for t, m, ok in s.targets]
    head += ["", "## Summary", "", table(["#", "target or comparison", "measured", ""], rows)]
    parts = ["\n".join(head)]
    for s in sections:
        parts.append(f"## {s.title}\n\n{s.body}\n\n_This benchmark took {s.seconds / 60:.1f} min._")
    return "\n\n".join(parts) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=HERE / "out", help="where the benchmark runs are kept (default benchmarks/out)")
    p.add_argument("--results", type=Path, default=HERE / "RESULTS.md", help="the Markdown file to (re)write")
    p.add_argument("--only", nargs="+", choices=[k for k, _ in SUITE], default=None,
                   help="run some benchmarks only (their inputs from earlier ones are then missing where they replay runs)")
    p.add_argument("--quick", action="store_true", help="tiny budgets, to check the suite itself")
    a = p.parse_args(argv)
    if a.only and a.results == HERE / "RESULTS.md":
        p.error("--only writes a partial report; give --results another path so RESULTS.md keeps one whole run")
    a.out.mkdir(parents=True, exist_ok=True)
    ctx = Context(out=a.out.resolve(), quick=a.quick)
    started = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    host = machine()
    t0 = time.perf_counter()
    sections = []
    for key, module in SUITE:
        if a.only and key not in a.only:
            continue
        print(f"[{time.strftime('%H:%M:%S')}] benchmark {key} ...", flush=True)
        t = time.perf_counter()
        section = module.run(ctx)
        section.seconds = time.perf_counter() - t
        sections.append(section)
        print(section.body, flush=True)
    total = time.perf_counter() - t0
    command = "python benchmarks/run_all.py" + (" " + " ".join(argv if argv is not None else sys.argv[1:])).rstrip()
    a.results.write_text(render(sections, started=started, host=host, command=command.strip(), total_s=total, quick=a.quick),
                         encoding="utf-8")
    doc = {"date": started, "machine": host, "quick": a.quick, "seconds": total,
           "benchmarks": {s.key: {"title": s.title, "seconds": s.seconds, "data": s.data} for s in sections}}
    (a.out / "results.json").write_text(json.dumps(doc, indent=2, default=str), encoding="utf-8")
    print(f"wrote {a.results} and {a.out / 'results.json'} ({total / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
