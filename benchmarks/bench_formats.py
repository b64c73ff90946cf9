"""12. Search quality of the two number formats: decimal (before) against the grid, same seeds and secrets.

pp with the embedded model (document form) on CartPole, Acrobot and Pendulum-v1: each (task, seed)
runs once per format with the same secrets (so the same warm-up, the same A and c; on the grid the
secret factor g multiplies A) and the same selection stage and final evaluation (20 fresh episodes
of the policy handed over), at benchmark 6's budget (10 warm-up + 50 LLM iterations). Each run is
audited.

With ``run_all.py --keep`` the runs already finished under ``--out`` are reused (an unfinished one
is started again); with ``--keep --collect`` nothing is started and the table holds the (task, seed)
pairs whose two runs have both finished: the rows say how many seeds each holds.
"""

from __future__ import annotations

import statistics
from typing import Any

from _common import Context, Section, config, finished, llm_calls, run_search, run_secrets, table, timings

from ppprops.privacy.audit import audit_run
from ppprops.summary import run_summary

TASKS = ("CartPole", "Pendulum-v1", "Acrobot")  # cheapest first: a partial run still fills whole rows
SEEDS = (0, 1, 2, 3, 4)
ITERATIONS = 50
FORMATS = (("decimal", "decimal (before)"), ("grid", "grid (now)"))



def run(ctx: Context) -> Section:
    rows, data, audits = [], {}, []
    iterations = 2 if ctx.quick else ITERATIONS
    done: dict[str, list[int]] = {task: [] for task in TASKS}
    for task in TASKS:
        for seed in SEEDS:
            secrets = None
            dirs = {fmt: ctx.dir("formats") / f"{task}-{seed}-{fmt}" for fmt, _ in FORMATS}
            if ctx.collect and not all(finished(d) for d in dirs.values()):
                continue
            for fmt, _ in FORMATS:
                cfg = config(task, warmup=10, iterations=iterations, seed=seed, final_episodes=20, number_format=fmt)
                if ctx.keep and finished(dirs[fmt]):
                    run_dir = dirs[fmt]
                else:
                    run_dir = run_search(cfg, dirs[fmt], secrets=secrets)
                secrets = secrets or run_secrets(run_dir)  # the second format reuses the first one's secrets
                s = run_summary(run_dir)
                calls = llm_calls(run_dir)
                t = [timings(c["response"]) for c in calls if c["ok"]]
                report = audit_run(run_dir)
                audits.append((f"{task}-{seed}-{fmt}", report.verdict().split(":")[0], bool(report.leaks or report.unverified)))
                data[f"{task}/{seed}/{fmt}"] = {
                    "final": s["final_eval"]["mean"], "best": (s["best"].get("search_best") or s["best"])["return"],
                    "requests": len(calls), "llm_s": sum(c["latency_s"] for c in calls),
                    "answer_tokens": sum(x.get("predicted_n", 0.0) for x in t),
                    "prompt_tokens": sum(x.get("prompt_n", 0.0) + x.get("cache_n", 0.0) for x in t),
                    "fallbacks": s["counts"]["fallback"], "audit": report.verdict().split(":")[0]}
            done[task].append(seed)
    for task in TASKS:
        for fmt, label in FORMATS:
            runs = [data[f"{task}/{seed}/{fmt}"] for seed in done[task]]
            if not runs:
                continue
            finals = [r["final"] for r in runs]
            req = sum(r["requests"] for r in runs)
            rows.append([task, label, len(runs), f"{statistics.fmean(finals):.1f}", f"{statistics.median(finals):.1f}",
                         f"{statistics.fmean(r['best'] for r in runs):.1f}", sum(r["fallbacks"] for r in runs),
                         f"{sum(r['llm_s'] for r in runs) / max(req, 1):.2f}",
                         f"{sum(r['prompt_tokens'] for r in runs) / max(req, 1):.0f}",
                         f"{sum(r['answer_tokens'] for r in runs) / max(req, 1):.0f}"])
    bad = [name for name, _, b in audits if b]
    body = [
        f"pp, embedded Gemma 3 270M, document form; up to {len(SEEDS)} seeds per task, 10 warm-up + {iterations} LLM iterations, "
        "selection stage (top 5 on 10 fresh episodes), final evaluation on 20 fresh episodes; both formats of a (task, seed) "
        "share their secrets.",
        "",
        table(["task", "format", "seeds", "final-evaluation mean", "median", "best search return", "fallbacks",
               "mean request (s)", "prompt tokens/request", "answer tokens/request"], rows),
        "",
        f"- `ppprops audit` on the {len(audits)} runs: " + ", ".join(f"{n} {v}" for n, v, _ in audits)
        + (f"; LEAK or UNVERIFIED on {', '.join(bad)}" if bad else "; none LEAK or UNVERIFIED") + ".",
    ]
    targets: list[tuple[str, str, bool | None]] = []
    for task in TASKS:
        if not done[task]:
            continue
        old = [data[f"{task}/{s}/decimal"]["final"] for s in done[task]]
        new = [data[f"{task}/{s}/grid"]["final"] for s in done[task]]
        met = statistics.fmean(new) >= statistics.fmean(old) and statistics.median(new) >= statistics.median(old)
        targets.append((f"{task}: grid no worse than decimal, final-evaluation mean and median ({iterations} iterations)",
                        f"mean {statistics.fmean(new):.1f} vs {statistics.fmean(old):.1f}; median "
                        f"{statistics.median(new):.1f} vs {statistics.median(old):.1f} ({len(done[task])} seeds)", met))
    out: dict[str, Any] = {"runs": data, "audits": audits}
    return Section("formats", "12. Search quality: decimal vs grid number format", "\n".join(body), out, targets=targets)
