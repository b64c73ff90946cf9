"""The benchmark suite: every figure of benchmarks/RESULTS.md, measured in one run.

    python benchmarks/run_all.py                 # about 2 hours on 2 idle cores; rewrites benchmarks/RESULTS.md
    python benchmarks/run_all.py --quick --results /tmp/RESULTS.md --out /tmp/bench   # tiny budgets: checks the suite runs
    python benchmarks/run_all.py --keep --only quality prompt readme # reuse the recorded grid, rewrite 3 sections

Needs the ``baselines`` and ``mujoco`` extras (CMA-ES; Ant and Humanoid). Runs are kept under
``--out`` (default benchmarks/out), so every figure can be traced back to a run store
(``ppprops show``, ``ppprops audit``). Benchmarks run one after another, never side by side,
except the quality grid, which uses both cores on purpose. Ratios compare things measured in this
same run; absolute times depend on the machine and its load, which the header records.

By default every benchmark starts afresh (the quality grid under ``--out`` is deleted first).
``--keep`` reuses a quality grid already recorded there: ``ppprops experiment`` skips its finished
runs and resumes the rest; ``--keep --collect`` starts nothing and reports only the finished runs
(for a grid still running in another process; each row says how many seeds it holds).

``--only`` runs some benchmarks and rewrites only their sections of ``--results``; the other
sections stay as they were. Every section ends with the date, the git commit and the command it
was measured with, and the summary table says the same for each row, so a partial rerun never
passes off older figures as new. (Benchmarks that replay runs of an earlier one need it in the
same invocation: ``prompt`` and ``cache`` use the quality grid's runs.)
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import sys
import time
from pathlib import Path

import bench_cache
import bench_eval
import bench_formats
import bench_hardened
import bench_history
import bench_labels
import bench_overhead
import bench_prompt
import bench_quality
import bench_readme
import bench_startup
import bench_threads
import bench_width
from _common import Context, Section, commit, machine, table

# Order matters: later benchmarks replay runs that earlier ones recorded (see Context.cache).
SUITE = (("quality", bench_quality), ("prompt", bench_prompt), ("labels", bench_labels), ("history", bench_history), ("cache", bench_cache),
         ("overhead", bench_overhead), ("eval", bench_eval), ("readme", bench_readme), ("startup", bench_startup),
         ("threads", bench_threads), ("formats", bench_formats), ("width", bench_width),
         ("hardened", bench_hardened))
HERE = Path(__file__).resolve().parent
SECTION_ORDER = ["6", "12", "7", "1", "11", "2", "3", "4", "5", "9", "10"]  # RESULTS.md order: the search itself first, as SUITE runs them


STATUS = {True: "met", False: "**not met**", None: "(no target)"}
_STAMP = re.compile(r"^_Measured (?P<when>.+?) at commit (?P<commit>\S+) with `(?P<command>[^`]*)`(?P<rest>.*)_$", re.M)
_TOOK = re.compile(r"^_This benchmark took (?P<min>[\d.]+) min\._$", re.M)


def stamp(section: Section, *, started: str, code: str, command: str) -> str:
    """The last line of a section: when, at which commit and with which command it was measured."""
    return f"_Measured {started} at commit {code or 'unknown'} with `{command}`; this benchmark took {section.seconds / 60:.1f} min._"


def kept_sections(text: str) -> tuple[dict[str, str], dict[str, list[list[str]]]]:
    """The sections of an existing RESULTS.md, by number ("6"), each ending in its stamp, and the
    summary rows of each (cells, the last one saying when it was measured). A file written before
    sections carried their own stamp gets its header's date and commit (the whole-suite run that
    wrote it)."""
    date = re.search(r"^- Date: (.+)$", text, re.M)
    code = re.search(r"^- Machine: .*\(([0-9a-f+changes]+)\)", text, re.M)
    cmd = re.search(r"^- Command: `([^`]*)`", text, re.M)
    old_when = f"{date.group(1) if date else 'an unknown date'}"
    old_commit = code.group(1) if code else "unknown"
    sections: dict[str, str] = {}
    for part in re.split(r"^## ", text, flags=re.M)[1:]:
        title = part.split("\n", 1)[0]
        num = title.split(". ", 1)[0]
        if not num.isdigit():
            continue
        body = part.rstrip("\n")
        if not _STAMP.search(body):
            took = _TOOK.search(body)
            line = (f"_Measured {old_when} at commit {old_commit} with `{cmd.group(1) if cmd else 'python benchmarks/run_all.py'}`"
                    f"{f'; this benchmark took {took.group(1)} min' if took else ''}._")
            body = _TOOK.sub(line, body) if took else body + "\n\n" + line
        sections[num] = "## " + body
    rows: dict[str, list[list[str]]] = {}
    summary = re.search(r"^## Summary\n\n(.*?)(?:\n\n|\Z)", text, re.M | re.S)
    for line in (summary.group(1).splitlines()[2:] if summary else []):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4:  # written before rows said when: the section's stamp says
            m = _STAMP.search(sections.get(cells[0], ""))
            cells.append(f"{m.group('when')} ({m.group('commit')})" if m else f"{old_when} ({old_commit})")
        if len(cells) >= 5:
            rows.setdefault(cells[0], []).append(cells[:5])
    return sections, rows


def render(sections: list[Section], *, started: str, host: str, command: str, total_s: float, quick: bool,
           code: str = "", previous: str | None = None) -> str:
    """RESULTS.md: the sections measured now, and (``previous``: the file's old text, with
    ``--only``) every other section of it as it was, each with its own date and commit."""
    head = [
        "# Benchmark results",
        "",
        "Written by `python benchmarks/run_all.py`; do not edit by hand, rerun it. Each section ends with the date, "
        "commit and command it was measured with; the summary's last column says the same for each row.",
        "",
        f"- Last run: {started}" + ("" if previous is None else " (some sections only; the others are older, see their dates)"),
        f"- Machine: {host}",
        f"- Command: `{command}`",
        f"- Wall time of this run: {total_s / 60:.1f} min",
    ]
    if quick:
        head += ["", "**Quick mode: tiny budgets that only check the suite runs. These figures mean nothing.**"]
    when = f"{started} ({code or 'unknown'})"
    parts_by_num: dict[str, str] = {}
    rows_by_num: dict[str, list[list[str]]] = {}
    if previous is not None:
        parts_by_num, rows_by_num = kept_sections(previous)
    for s in sections:
        num = s.title.split(". ", 1)[0]
        parts_by_num[num] = (f"## {s.title}\n\n{s.body}\n\n" + stamp(s, started=started, code=code, command=command)
                             + ("\n\n**Quick mode: these figures mean nothing.**" if quick else ""))
        rows_by_num[num] = [[num, t, m, STATUS[ok], when] for t, m, ok in s.targets]
    order = [s.title.split(". ", 1)[0] for s in sections] if previous is None else \
        sorted(parts_by_num, key=lambda n: (SECTION_ORDER.index(n) if n in SECTION_ORDER else 99, n))
    rows = [r for n in order for r in rows_by_num.get(n, [])]
    head += ["", "## Summary", "", table(["#", "target or comparison", "measured", "", "measured at (commit)"], rows)]
    return "\n\n".join(["\n".join(head), *(parts_by_num[n] for n in order)]) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=HERE / "out", help="where the benchmark runs are kept (default benchmarks/out)")
    p.add_argument("--results", type=Path, default=HERE / "RESULTS.md", help="the Markdown file to (re)write")
    p.add_argument("--only", nargs="+", choices=[k for k, _ in SUITE], default=None,
                   help="run some benchmarks only and rewrite only their sections of --results (the others keep their own "
                        "date and commit); inputs from benchmarks not run are missing where they replay runs")
    p.add_argument("--keep", action="store_true",
                   help="reuse the quality grid already recorded under --out (finished runs kept, the rest resumed) "
                        "instead of deleting it and starting afresh")
    p.add_argument("--collect", action="store_true",
                   help="with --keep: start nothing, report only the grid's finished runs (a grid still running elsewhere)")
    p.add_argument("--quick", action="store_true",
                   help="tiny budgets, to check the suite itself (a few minutes): one seed of the quality grid on CartPole "
                        "and Acrobot, one LLM iteration per search, answers cut to a few tokens; the figures mean nothing")
    a = p.parse_args(argv)
    if a.collect and not a.keep:
        p.error("--collect reports a recorded grid: give --keep too")
    a.out.mkdir(parents=True, exist_ok=True)
    ctx = Context(out=a.out.resolve(), quick=a.quick, keep=a.keep, collect=a.collect)
    code = commit()
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
    previous = a.results.read_text(encoding="utf-8") if a.only and a.results.exists() else None
    a.results.write_text(render(sections, started=started, host=host, command=command.strip(), total_s=total, quick=a.quick,
                                code=code, previous=previous), encoding="utf-8")
    doc = {"date": started, "commit": code, "machine": host, "quick": a.quick, "seconds": total, "only": a.only,
           "keep": a.keep, "collect": a.collect,
           "benchmarks": {s.key: {"title": s.title, "seconds": s.seconds, "data": s.data, "targets": s.targets} for s in sections}}
    (a.out / "results.json").write_text(json.dumps(doc, indent=2, default=str), encoding="utf-8")
    print(f"wrote {a.results} and {a.out / 'results.json'} ({total / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
