"""Request pacing: its cost in wall time, and what the provider's clock gives with it off and on.

A rig stepped in real time (each CartPole/Acrobot episode runs in the real env, then waits
``--step-ms`` of wall time per step, as a robot would), driven through ask/tell; the offline
stand-in optimizer answers at once (``privacy.simulate.EchoOptimizer``), so the wall time is the
rig's plus the pacing's. For each task, method (pp, pp-hardened) and pacing (off, on), ``--seeds``
runs with the same run seeds; per configuration: wall time (and its ratio to the same method
without pacing), the best search return, and the audit's timing measurement (``privacy.timing``:
Spearman of the gaps with the episode steps, the runs where it reports the channel, the best
shown raw return's error through the calibrated clock).

    python benchmarks/bench_pacing.py --tasks CartPole,Acrobot --seeds 3 --warmup 5 --iterations 10 --step-ms 2

Pacing changes when requests leave, never what they hold: with the same secrets and answers the
search is the same, so any difference in the best return between paced and unpaced runs comes
from the draws of fresh secrets per run, not from the pacing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def one_run(out: Path, task_name: str, method: str, pace: bool, seed: int, warmup: int, iterations: int, step_s: float) -> dict[str, float]:
    from ppprops.evaluation import make_policy, run_episode
    from ppprops.privacy.audit import audit_run
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.settings import build_config
    from ppprops.study import Study
    from ppprops.tasks import get_task

    task = get_task(task_name)
    cfg = build_config({"method": method, "warmup": warmup, "iterations": iterations, "final_episodes": 0, "select_top": 0,
                        "seed": seed, "prompt_form": "chat", "pace_requests": pace}, task=task)
    env = task.make_env()
    t0 = time.monotonic()
    best = -np.inf
    with Study.create(cfg, out, llm=EchoOptimizer(cfg.llm)) as study:
        while not study.done:
            trial = study.ask()
            eps = [run_episode(task, env, make_policy(task, np.asarray(trial.theta), env), s) for s in trial.seeds]
            steps = sum(float(e.diagnostics.get("episode_length", 0)) for e in eps)
            time.sleep(step_s * steps)  # the rig runs in real time
            study.tell(trial, [e.ret for e in eps], components=[e.components for e in eps], diagnostics=[e.diagnostics for e in eps])
            best = max(best, float(np.mean([e.ret for e in eps])))
    wall = time.monotonic() - t0
    env.close()
    report = audit_run(out, simulate=False)
    (note,) = [n for n in report.notes if n.startswith("request timing")] or ["request timing: Spearman nan"]
    rho = float(note.split("Spearman ")[1].split(" ")[0]) if "Spearman " in note else float("nan")
    flagged = [f for f in report.findings if f.kind in ("request_timing", "request-timing")]
    err = float("nan")
    if flagged and "within " in flagged[0].detail:
        err = float(flagged[0].detail.split("raw return within ")[1].split("%")[0]) if "raw return within " in flagged[0].detail else err
    return {"wall": wall, "best": best, "rho": rho, "flagged": float(bool(flagged)), "err": err}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="CartPole,Acrobot")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--step-ms", type=float, default=2.0)
    a = p.parse_args(argv)
    rows = []
    base = Path(tempfile.mkdtemp(prefix="bench-pacing-"))
    for task in [t.strip() for t in a.tasks.split(",") if t.strip()]:
        for method in ("pp", "pp-hardened"):
            got: dict[bool, list[dict[str, float]]] = {}
            for pace in (False, True):
                got[pace] = [one_run(base / f"{task}-{method}-{pace}-{s}", task, method, pace, s, a.warmup, a.iterations, a.step_ms / 1000)
                             for s in range(a.seeds)]
                print(f"{task} {method} pace={pace}: done", file=sys.stderr)
            plain = statistics.mean(r["wall"] for r in got[False])
            for pace in (False, True):
                rs = got[pace]
                walls = [r["wall"] for r in rs]
                errs = [r["err"] for r in rs if r["err"] == r["err"]]
                rows.append(f"| {task} | {method} | {'on' if pace else 'off'} | {statistics.mean(walls):.1f} | "
                            f"{statistics.mean(walls) / plain:.2f} | {statistics.mean(r['best'] for r in rs):.1f} | "
                            f"{statistics.median(r['rho'] for r in rs):+.2f} | {int(sum(r['flagged'] for r in rs))}/{len(rs)} | "
                            f"{(f'{statistics.median(errs):.3g}%') if errs else '-'} |")
    print("| task | method | pacing | wall s (mean) | wall / unpaced | best search return (mean) | timing rho (median) | "
          "timing channel reported | best raw return via clock (median) |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
