"""Soak test: a long PP-ProPS run against the fault-injection server, then an audit of the store.

Starts ``python -m ppprops.testing.fault_server`` (every fault kind at ``--fault-rate``; the
other requests answered by the server-and-model personas, drawn per request: gpt-oss via vLLM,
Ollama and llama.cpp, harmony markup, R1 think tags, DeepSeek, OpenAI reasoning models, Gemini,
...), runs ``ppprops run`` against it with short backoff settings, ``--structured auto`` and
``--on-llm-failure skip``, optionally ``kill -9``s the run at random moments and resumes it, and
then checks that every evaluation is recorded exactly once, the store passes SQLite's integrity
check, (without kills) every HTTP request the server saw is one ``llm_calls`` row, no LLM
candidate equals an earlier candidate at the precision the prompt prints (a history vector taken
as a proposal), and every LLM candidate is a vector the server proposed.

    python benchmarks/soak.py                       # 500 LLM iterations, 30% faults
    python benchmarks/soak.py --iterations 100 --kills 5 --json

Exit status 0 when every check passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
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

import numpy as np


def _start_server(a: argparse.Namespace, answers_file: Path) -> tuple[subprocess.Popen[str], str]:
    cmd = [sys.executable, "-m", "ppprops.testing.fault_server", "--port", "0", "--synthetic",
           "--fault-rate", str(a.fault_rate), "--kinds", a.kinds, "--seed", str(a.seed),
           "--retry-after", str(a.retry_after), "--timeout-delay", str(a.timeout * 1.5),
           "--delay-max", str(a.delay_max), "--max-seconds", str(a.max_seconds), "--personas", a.personas,
           "--answers-file", str(answers_file)]
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


def _proposal_checks(out: Path, answers: list[list[float]]) -> tuple[int, int, int]:
    """(LLM candidates, those equal to an earlier candidate as the prompt prints it, those that are
    no vector the server proposed). A server vector becomes a candidate decoded, clipped to the
    box and encoded again, with the run's own secrets."""
    from ppprops.client.hardening import codec_for
    from ppprops.proposers.base import clip_to_box
    from ppprops.runner import load_run
    from ppprops.wire.numbers import fmt, fmt_vector

    store, config, secrets = load_run(out)
    try:
        cands = store.candidates()
    finally:
        store.close()
    codec = codec_for(secrets, config.make_task(), config.encoding)

    def printed(v: np.ndarray) -> str:
        if config.prompt_params == "list":
            return fmt_vector(list(v), config.decimals, digits=config.digits(), sep=",")
        return ", ".join(fmt(x, config.decimals) for x in v)

    seen: set[str] = set()
    llm = repeated = 0
    for c in cands:
        text = printed(c.params_enc)
        if c.source == "llm":
            llm += 1
            repeated += text in seen
        seen.add(text)
    with np.errstate(over="ignore", invalid="ignore"):
        expected = np.array([codec.encode(clip_to_box(codec.decode(np.asarray(a)), config.box)[0])
                             for a in answers if len(a) == len(secrets.a) and all(map(math.isfinite, a))])
    foreign = 0
    for c in cands:
        if c.source == "llm":
            foreign += not (len(expected) and np.isclose(expected, c.params_enc, rtol=1e-9, atol=1e-9).all(axis=1).any())
    return llm, repeated, foreign


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="CartPole")
    p.add_argument("--iterations", type=int, default=500)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--final-episodes", type=int, default=5)
    p.add_argument("--fault-rate", type=float, default=0.3)
    p.add_argument("--kinds", default="all", help="fault kinds for the server (default all)")
    p.add_argument("--personas", default="all", help="server personas answering the other requests (default all)")
    p.add_argument("--structured", default="auto", help="the run's --structured (default auto)")
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
    answers_file = out.parent / f".{out.name}.answers.json"
    server, url = _start_server(a, answers_file)
    run_cmd = [sys.executable, "-m", "ppprops", "run", "--env", a.env, "--method", "pp", "--warmup", str(a.warmup),
               "--iterations", str(a.iterations), "--final-episodes", str(a.final_episodes), "--seed", str(a.seed),
               "--out", str(out), "--quiet", "--base-url", url, "--model", "fault-synthetic", "--structured", a.structured,
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

    from ppprops.summary import run_summary

    s = run_summary(out)
    with sqlite3.connect(out / "run.sqlite") as con:
        idx = [r[0] for r in con.execute("SELECT idx FROM candidates ORDER BY idx")]
        integrity = con.execute("PRAGMA integrity_check").fetchone()[0]
        rows = int(con.execute("SELECT COUNT(*) FROM llm_calls").fetchone()[0])
    c = s["counts"]
    answers = [x["params"] for x in json.loads(answers_file.read_text(encoding="utf-8"))]
    llm, history_vectors, foreign = _proposal_checks(out, answers)
    checks = {
        "every_evaluation_once": idx == list(range(total)),
        "integrity_ok": integrity == "ok",
        "finished": s["status"] == "finished" and s["final_eval"] is not None,
        "every_request_recorded_once": rows == stats["requests"] if not kills else None,
        "no_history_vector_as_proposal": history_vectors == 0,
        "every_llm_proposal_from_the_server": foreign == 0,
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
        "llm_candidates": llm,
        "history_vectors_as_proposals": history_vectors,
        "llm_candidates_not_proposed_by_the_server": foreign,
        "request_adaptations": [x["change"] for x in s["llm_adaptations"]],
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
        print("  personas " + ", ".join(f"{k} x{v}" for k, v in stats.get("personas", {}).items()))
        print(f"  client   {rows} requests recorded, {c['retries']} retries; failed tries: "
              + (", ".join(f"{k} x{v}" for k, v in c["transport_failures"].items()) or "none"))
        print("  answers  unusable: " + (", ".join(f"{k} x{v}" for k, v in c["answer_failures"].items()) or "none")
              + f"; {c['answers_from_reasoning']} taken from reasoning")
        reasons = ", ".join(f"{k} x{v}" for k, v in c["fallback_reasons"].items()) or "none"
        print(f"  fallback {c['fallback']} ({reasons})")
        for x in s["llm_adaptations"]:
            print(f"  adapted  at LLM iteration {x['iteration']}: {x['change']}")
        print(f"  proposals {llm} LLM candidates: {history_vectors} equal to an earlier candidate as printed "
              f"(history vectors evaluated as proposals), {foreign} not proposed by the server")
        if kills:
            print(f"  kills    kill -9 at {kills} recorded candidates, each resumed")
        print("  checks   " + ", ".join(f"{k}={'n/a' if v is None else ('ok' if v else 'FAILED')}" for k, v in checks.items()))
    return 0 if all(v is not False for v in checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
