"""Soak test: a long PP-ProPS run against the fault-injection server, then an audit of the store.

Starts ``python -m ppprops.testing.fault_server`` (synthetic answers, every fault kind at
``--fault-rate``), runs ``ppprops run`` against it with short backoff settings and
``--on-llm-failure skip``, optionally ``kill -9``s the run at random moments and resumes it,
and then checks that every evaluation is recorded exactly once, the store passes SQLite's
integrity check, and (without kills) every HTTP request the server saw is one ``llm_calls`` row.

    python benchmarks/soak.py                       # 500 LLM iterations, 30% faults
    python benchmarks/soak.py --iterations 100 --kills 5 --json

Exit status 0 when every check passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _start_server(a: argparse.Namespace) -> tuple[subprocess.Popen[str], str]:
    cmd = [sys.executable, "-m", "ppprops.testing.fault_server", "--port", "0", "--synthetic",
           "--fault-rate", str(a.fault_rate), "--kinds", a.kinds, "--seed", str(a.seed),
           "--retry-after", str(a.retry_after), "--timeout-delay", str(a.timeout * 1.5),
           "--delay-max", str(a.delay_max), "--max-seconds", str(a.max_seconds)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    if not line.startswith("listening "):
        proc.kill()
        raise SystemExit(f"soak: the fault server did not start ({line!r})")
    return proc, line.split()[1]


def _stop_server(proc: subprocess.Popen[str]) -> dict[str, Any]:
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    return dict(json.loads(out.strip().splitlines()[-1]))


def _count(db: Path) -> int:
    try:
        with sqlite3.connect(db, timeout=5) as con:
            return int(con.execute("SELECT COUNT(*) FROM candidates").fetchone()[0])
    except sqlite3.Error:
        return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="CartPole")
    p.add_argument("--iterations", type=int, default=500)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--final-episodes", type=int, default=5)
    p.add_argument("--fault-rate", type=float, default=0.3)
    p.add_argument("--kinds", default="all", help="fault kinds for the server (default all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=1.0, help="client timeout per request; 'timeout' faults stall 1.5x this")
    p.add_argument("--retries", type=int, default=6)
    p.add_argument("--retry-base-delay", type=float, default=0.05)
    p.add_argument("--retry-after", type=float, default=0.2, help="Retry-After the server sends with a 429")
    p.add_argument("--delay-max", type=float, default=0.2)
    p.add_argument("--kills", type=int, default=0, help="kill -9 the run this many times at random moments, then resume")
    p.add_argument("--max-seconds", type=float, default=1800.0, help="the fault server stops by itself after this")
    p.add_argument("--out", type=Path, default=None, help="run directory (default: a fresh temporary one)")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    a = p.parse_args(argv)

    out = a.out or Path(tempfile.mkdtemp(prefix="ppprops-soak-")) / "run"
    total = a.warmup + a.iterations
    server, url = _start_server(a)
    run_cmd = [sys.executable, "-m", "ppprops", "run", "--env", a.env, "--method", "pp", "--warmup", str(a.warmup),
               "--iterations", str(a.iterations), "--final-episodes", str(a.final_episodes), "--seed", str(a.seed),
               "--out", str(out), "--quiet", "--base-url", url, "--model", "fault-synthetic", "--structured", "json_schema",
               "--timeout", str(a.timeout), "--retries", str(a.retries), "--retry-base-delay", str(a.retry_base_delay),
               "--retry-max-delay", "1", "--retry-after-cap", "1", "--on-llm-failure", "skip"]
    resume_cmd = [sys.executable, "-m", "ppprops", "resume", str(out), "--quiet"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    rng = random.Random(a.seed)
    kills: list[int] = []
    t0 = time.perf_counter()
    try:
        targets = sorted(rng.sample(range(1, total), min(a.kills, total - 1)))
        for target in targets:  # kill once that many candidates are recorded (spread over the run), then resume
            cmd = run_cmd if not (out / "run.sqlite").exists() else resume_cmd
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
            while _count(out / "run.sqlite") < target and proc.poll() is None:
                time.sleep(0.01)
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
            kills.append(_count(out / "run.sqlite"))
        cmd = run_cmd if not (out / "run.sqlite").exists() else resume_cmd
        done = subprocess.run(cmd, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
    finally:
        stats = _stop_server(server)
    if done.returncode != 0:
        print(done.stderr.strip(), file=sys.stderr)
        return 1

    from ppprops.report import run_summary

    s = run_summary(out)
    with sqlite3.connect(out / "run.sqlite") as con:
        idx = [r[0] for r in con.execute("SELECT idx FROM candidates ORDER BY idx")]
        integrity = con.execute("PRAGMA integrity_check").fetchone()[0]
        rows = int(con.execute("SELECT COUNT(*) FROM llm_calls").fetchone()[0])
    c = s["counts"]
    checks = {
        "every_evaluation_once": idx == list(range(total)),
        "integrity_ok": integrity == "ok",
        "finished": s["status"] == "finished" and s["final_eval"] is not None,
        "every_request_recorded_once": rows == stats["requests"] if not kills else None,
    }
    figures = {
        "run_dir": str(out),
        "iterations": a.iterations,
        "evaluations": len(idx),
        "wall_s": round(wall, 1),
        "server": stats,
        "llm_calls_recorded": rows,
        "transport_failures": c["transport_failures"],
        "retries": c["retries"],
        "answer_failures": c["answer_failures"],
        "answers_from_reasoning": c["answers_from_reasoning"],
        "fallbacks": c["fallback"],
        "fallback_reasons": c["fallback_reasons"],
        "llm_unavailable": c["llm_unavailable"],
        "kills_at_candidates": kills,
        "best_return": s["best"]["return"] if s["best"] else None,
        "checks": checks,
    }
    if a.json:
        print(json.dumps(figures))
    else:
        inj = stats["injected"]
        print(f"soak: {a.iterations} LLM iterations ({len(idx)} evaluations) in {wall:.1f} s, run {out}")
        print(f"  server   {stats['requests']} requests, {stats['injected_total']} faults injected "
              f"({stats['injected_total'] / max(1, stats['requests']):.0%})")
        print("  injected " + ", ".join(f"{k} x{v}" for k, v in inj.items()))
        print(f"  client   {rows} requests recorded, {c['retries']} retries; failed tries: "
              + (", ".join(f"{k} x{v}" for k, v in c["transport_failures"].items()) or "none"))
        print("  answers  unusable: " + (", ".join(f"{k} x{v}" for k, v in c["answer_failures"].items()) or "none")
              + f"; {c['answers_from_reasoning']} taken from reasoning")
        reasons = ", ".join(f"{k} x{v}" for k, v in c["fallback_reasons"].items()) or "none"
        print(f"  fallback {c['fallback']} ({reasons})")
        if kills:
            print(f"  kills    kill -9 at {kills} recorded candidates, each resumed")
        print("  checks   " + ", ".join(f"{k}={'n/a' if v is None else ('ok' if v else 'FAILED')}" for k, v in checks.items()))
    return 0 if all(v is not False for v in checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
