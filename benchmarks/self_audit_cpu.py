"""CPU time of the audit a finished run prints about itself (the last line of ``ppprops run``).

Each measurement is a fresh process that first makes a 60-candidate CartPole run offline (10
warm-up policies and 50 LLM iterations answered by ``privacy.simulate.EchoOptimizer``, a fixed
seed, no final evaluation), as ``ppprops run`` would have just done, and then times with
``time.process_time`` one of:

- ``finished``: what ``run`` and ``resume`` do at the end: the summary (``summary.run_summary``,
  ``format_summary``) and the privacy audit line in its default mode (``self_audit_line``);
- ``quick``: ``audit_run(DIR, attacks=False)``, the transcript checks alone;
- ``full``: ``audit_run(DIR)``, every attack too (what ``ppprops audit DIR`` runs).

    PYTHONPATH=src python benchmarks/self_audit_cpu.py                      # 5 runs of each, pp
    PYTHONPATH=src python benchmarks/self_audit_cpu.py --runs 5 --method pp-hardened --what finished quick
    PYTHONPATH=src python benchmarks/self_audit_cpu.py --task Humanoid-Torso --iterations 30 --what quick

A measurement the code under test cannot make (``quick`` before ``audit_run`` took ``attacks``)
is reported as not available.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import io
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WHAT = ("finished", "quick", "full")


def _child(what: str, a: argparse.Namespace, out: Path) -> dict[str, object]:
    from ppprops.privacy.audit import audit_run
    from ppprops.privacy.commands import self_audit_line
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.runner import start
    from ppprops.settings import build_config
    from ppprops.tasks import get_task

    config = build_config({"method": a.method, "warmup": a.warmup, "iterations": a.iterations, "seed": a.seed, "final_episodes": 0},
                          task=get_task(a.task))
    start(config, out, llm=EchoOptimizer(config.llm))
    if what == "quick" and "attacks" not in inspect.signature(audit_run).parameters:
        return {"what": what, "cpu_s": None}
    sink = io.StringIO()
    t0, w0 = time.process_time(), time.perf_counter()
    if what == "finished":
        from ppprops.summary import format_summary, run_summary

        with contextlib.redirect_stdout(sink):
            print(format_summary(run_summary(out)))
            print(self_audit_line(out))
        line = sink.getvalue().strip().splitlines()[-1]
    elif what == "quick":
        line = audit_run(out, attacks=False).verdict()
    else:
        line = audit_run(out).verdict()
    return {"what": what, "cpu_s": time.process_time() - t0, "wall_s": time.perf_counter() - w0, "line": line}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=5, help="fresh processes per measurement (default 5)")
    p.add_argument("--method", default="pp", help="the run's method (default pp)")
    p.add_argument("--seed", type=int, default=12345, help="the run's seed (default 12345)")
    p.add_argument("--task", default="CartPole", help="the run's task (default CartPole)")
    p.add_argument("--warmup", type=int, default=10, help="warm-up policies (default 10)")
    p.add_argument("--iterations", type=int, default=50, help="LLM iterations (default 50)")
    p.add_argument("--what", nargs="+", choices=WHAT, default=list(WHAT), help="what to time (default all)")
    p.add_argument("--child", nargs=2, metavar=("WHAT", "DIR"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child:
        print(json.dumps(_child(a.child[0], a, Path(a.child[1]))))
        return 0
    for what in a.what:
        times: list[float] = []
        line = ""
        for i in range(a.runs):
            with tempfile.TemporaryDirectory() as tmp:
                cmd = [sys.executable, __file__, "--method", a.method, "--seed", str(a.seed), "--task", a.task, "--warmup",
                       str(a.warmup), "--iterations", str(a.iterations), "--child", what, str(Path(tmp) / "run")]
                proc = subprocess.run(cmd, capture_output=True, text=True, check=True)
            doc = json.loads(proc.stdout.strip().splitlines()[-1])
            if doc["cpu_s"] is None:
                break
            times.append(float(doc["cpu_s"]))
            line = str(doc["line"])
            print(f"  {what} #{i + 1}: {doc['cpu_s']:.3f} s CPU ({doc['wall_s']:.3f} s wall)", file=sys.stderr)
        if not times:
            print(f"{what}: not available in this version")
            continue
        print(f"{what}: CPU median {statistics.median(times):.2f} s, min {min(times):.2f}, max {max(times):.2f} "
              f"({len(times)} runs: {', '.join(f'{t:.2f}' for t in times)})")
        print(f"  its line: {line[:200]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
