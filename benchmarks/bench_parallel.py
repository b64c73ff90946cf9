"""Wall time of one search at --parallel 1 and --parallel P against an endpoint with a fixed latency
that serves requests side by side (the fault server's --latency and --concurrency), side by side
from one run.

    python benchmarks/bench_parallel.py                        # CartPole pp, 10 + 50, 2 s latency, P = 1 vs 4
    python benchmarks/bench_parallel.py --latency 1 --iterations 20 --json
    flock /work/llm.lock python benchmarks/bench_parallel.py --embedded --widths 1,2,4 --warmup 4 --iterations 8

With ``--embedded`` the runs use the embedded model (P slots at --parallel P; 1 worker each, the
cores are the model's) instead of the fault server; the table adds the tokens written per second
over the search. Run it under the machine's model lock.

Each run is ``ppprops run`` in its own process (P = 1 with 1 worker, P = P with P workers), the
same seed; the server answers with synthetic vectors after ``--latency`` seconds, at most
``--concurrency`` at once. Prints a Markdown table (or JSON): wall time, LLM calls, the most
requests in flight, the ratio. No model runs: no lock is needed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "src"))

from ppprops.store import open_store  # noqa: E402
from ppprops.testing.fault_server import FaultConfig, FaultServer  # noqa: E402


def one(width: int, workers: int, a: argparse.Namespace, out: Path) -> dict[str, Any]:
    cfg = FaultConfig(fault_rate=0.0, seed=a.seed, latency_s=a.latency, concurrency=a.concurrency)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "ppprops", "run", "--env", a.env, "--method", a.method, "--warmup", str(a.warmup),
           "--iterations", str(a.iterations), "--seed", str(a.seed), "--parallel", str(width), "--workers", str(workers),
           "--out", str(out), "--quiet"]
    if a.embedded:
        t0 = time.monotonic()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall = time.monotonic() - t0
        stats = {"most_in_flight": None}
    else:
        with FaultServer(cfg) as server:
            t0 = time.monotonic()
            proc = subprocess.run([*cmd, "--base-url", server.base_url, "--model", "m"], env=env, capture_output=True, text=True)
            wall = time.monotonic() - t0
            stats = server.stats()
    if proc.returncode != 0:
        raise SystemExit(f"P={width}: ppprops run failed: {proc.stderr.strip()}")
    with open_store(out) as store:
        cands = store.candidates()
        calls = store.llm_calls()
        fe = store.final_eval()
        times = store.candidate_times()
    search = [t for t in times if t[1] not in ("warmup", "reeval")]
    warm = [t for t in times if t[1] == "warmup"]
    llm_s = search[-1][3] - warm[-1][3] if search and warm else None
    tokens = sum(int(c["completion_tokens"] or 0) for c in calls)
    return {"P": width, "workers": workers, "wall_s": round(wall, 1),
            "search_s": round(search[-1][3] - times[0][3], 1) if search else None,
            "llm_phase_s": None if llm_s is None else round(llm_s, 1), "tokens": tokens,
            "tokens_per_s": None if not llm_s else round(tokens / llm_s, 1), "candidates": len(cands), "llm_calls": len(calls),
            "llm_candidates": sum(c.source in ("llm", "fallback") for c in cands), "most_in_flight": stats["most_in_flight"],
            "final_mean": None if fe is None else round(fe.mean, 1)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="CartPole")
    p.add_argument("--method", default="pp")
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--iterations", type=int, default=50)
    p.add_argument("--parallel", type=int, default=4)
    p.add_argument("--latency", type=float, default=2.0)
    p.add_argument("--concurrency", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.add_argument("--embedded", action="store_true", help="the embedded model instead of the fault server (run under its lock)")
    p.add_argument("--widths", default=None, help="with --embedded: the P values, e.g. 1,2,4 (1 worker each)")
    a = p.parse_args()
    if a.embedded:
        widths = [int(w) for w in (a.widths or "1,2,4").split(",")]
        with tempfile.TemporaryDirectory() as tmp:
            rows = [one(w, 1, a, Path(tmp) / f"p{w}") for w in widths]
        print(json.dumps({"rows": rows}) if a.json else "\n".join(
            [f"{a.env} {a.method}, {a.warmup} + {a.iterations}, embedded model\n",
             "| P (slots) | wall (s) | LLM phase (s) | LLM calls | completion tokens | tokens/s over the LLM phase | final mean |",
             "|---|---|---|---|---|---|---|"]
            + [f"| {r['P']} | {r['wall_s']} | {r['llm_phase_s']} | {r['llm_calls']} | {r['tokens']} | {r['tokens_per_s']} | "
               f"{r['final_mean']} |" for r in rows]))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        rows = [one(w, k, a, Path(tmp) / f"p{w}w{k}") for w, k in ((1, 1), (a.parallel, a.parallel), (a.parallel, 1))]
    ratio = rows[0]["wall_s"] / rows[1]["wall_s"]
    search_ratio = rows[0]["search_s"] / rows[1]["search_s"]
    if a.json:
        print(json.dumps({"rows": rows, "speedup": round(ratio, 2), "search_speedup": round(search_ratio, 2)}))
        return 0
    print(f"{a.env} {a.method}, {a.warmup} + {a.iterations}, endpoint latency {a.latency:g} s, {a.concurrency} served at once\n")
    print("| P | workers | wall (s) | first to last search candidate (s) | candidates | LLM calls | LLM candidates | "
          "most requests in flight | final mean |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['P']} | {r['workers']} | {r['wall_s']} | {r['search_s']} | {r['candidates']} | {r['llm_calls']} | "
              f"{r['llm_candidates']} | {r['most_in_flight']} | {r['final_mean']} |")
    print(f"\n- speed-up at P = {a.parallel} with {a.parallel} workers: **{ratio:.2f}x** wall, {search_ratio:.2f}x over the "
          "search (target at least 3x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
