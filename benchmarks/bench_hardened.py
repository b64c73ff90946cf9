"""16. What pp-hardened with request pacing costs against pp: search quality and wall time.

A grid (``benchmarks/hardened.toml``) run with ``ppprops experiment`` on both cores (one llama.cpp
thread per run): pp and pp-hardened with ``--pace-requests on`` on benchmark 6's budget (10 warm-up
+ 50 proposals of the embedded model, document form, the same selection stage and a final
evaluation on 20 fresh episodes), the same run seeds. The hardened arm changes what the provider
sees (secret origins, warped parameters and rewards, coarsened diagnostics, an encoded warm-up) and
when requests leave (pacing); pacing alone never changes a request's bytes, so a quality difference
between the arms is the hardening's, and the wall-time difference is both.

Per task and arm: the final evaluation (mean (std) and median over seeds), the quality cost of the
hardened arm relative to pp (the difference of the means over the absolute pp mean; target at most
5%), the search phase's wall time (from the last warm-up candidate to the last proposal), the LLM's
share of it (the sum of request latencies), the time between an answer and the next request (the
gap the pacer pads), and ``ppprops audit``'s verdicts. Tasks are benchmark 6's, cheapest first
(a request of the embedded model on one llama.cpp thread here: Pendulum-v1 and CartPole a few
seconds, Acrobot about 12 s, Ant-Ultra about 30 s, so an Ant-Ultra run takes about half an hour).

``--keep`` reuses the grid recorded under ``--out``/hardened (finished runs kept, the rest resumed);
``--keep --collect`` starts nothing and reports the seeds finished in both arms.
"""

from __future__ import annotations

import statistics
import subprocess
from collections import defaultdict
from pathlib import Path
from typing import Any

from _common import Context, Section, grid_dir, llm_calls, mean_std, table

from ppprops.privacy.audit import audit_run
from ppprops.store import open_store
from ppprops.summary import run_summary

SPEC = Path(__file__).with_name("hardened.toml")
TASKS = ("Pendulum-v1", "CartPole", "Acrobot", "Ant-Ultra")
ARMS = (("pp", "pp"), ("pp-hardened", "pp-hardened, paced"))
TARGET = 0.05  # the hardened arm's quality cost, relative to pp's mean final return


def _measure(run_dir: Path, s: dict[str, Any]) -> dict[str, Any]:
    """One finished run's figures (seconds are wall-clock, from the store's own timestamps)."""
    calls = sorted(llm_calls(run_dir), key=lambda c: float(c["created"]))
    with open_store(run_dir) as store:
        times = store.candidate_times()
    warm = [t[3] for t in times if t[1] == "warmup"]
    search = [t[3] for t in times if t[1] not in ("warmup", "reeval")]
    gaps = [float(b["created"]) - (float(a["created"]) + float(a["latency_s"] or 0.0)) for a, b in zip(calls, calls[1:])]
    report = audit_run(run_dir)
    return {"final": s["final_eval"]["mean"], "search_s": search[-1] - warm[-1] if search and warm else 0.0,
            "llm_s": sum(float(c["latency_s"] or 0.0) for c in calls), "gap_s": statistics.median(gaps) if gaps else 0.0,
            "requests": len(calls), "verdict": report.verdict().split(":")[0], "seed": s["seed"]}


def _interval(data: dict[str, list[dict[str, Any]]], task: str, cost: float) -> str:
    """The cost's 95% interval over the seeds' spread (normal, Welch standard error), or "" for one seed."""
    pp, hard = ([x["final"] for x in data[f"{task}/{arm}"]] for arm, _ in ARMS)
    if len(pp) < 2:
        return ""
    half = 1.96 * (statistics.variance(pp) / len(pp) + statistics.variance(hard) / len(hard)) ** 0.5 / abs(statistics.fmean(pp))
    return f"; 95% interval {cost - half:+.1%} to {cost + half:+.1%} over the seeds' spread"


def run(ctx: Context) -> Section:
    out, cmd, reused = grid_dir(ctx, "hardened", SPEC)
    if ctx.quick:
        cmd += ["--seeds", "1", "--tasks", "Pendulum-v1", "--warmup", "3", "--iterations", "2", "--final-episodes", "1"]
    if not ctx.collect:  # the cheaper task first: a grid stopped halfway still holds its whole rows
        for only in ([[]] if ctx.quick else [["--tasks", task] for task in TASKS]):
            subprocess.run([*cmd, *only], check=True)
    runs: dict[tuple[str, str, int], dict[str, Any]] = {}
    for run_dir in sorted(p.parent for p in out.glob("runs/*/run.sqlite")):
        s = run_summary(run_dir)
        if s["status"] == "finished" and s.get("final_eval"):
            runs[(s["env"], s["method"], int(s["seed"]))] = _measure(run_dir, s)
    rows: list[list[Any]] = []
    data: dict[str, list[dict[str, Any]]] = {}
    targets: list[tuple[str, str, bool | None]] = []
    for task in TASKS:
        seeds = sorted({seed for (t, _, seed) in runs if t == task and all((task, arm, seed) in runs for arm, _ in ARMS)})
        if not seeds:
            continue
        means: dict[str, float] = {}
        for arm, label in ARMS:
            r = [runs[(task, arm, seed)] for seed in seeds]
            data[f"{task}/{arm}"] = r
            final = [x["final"] for x in r]
            means[arm] = statistics.fmean(final)
            cost_cell = "" if arm == "pp" else f"{(means['pp'] - means[arm]) / abs(means['pp']):+.1%}"
            verdicts: dict[str, int] = defaultdict(int)
            for x in r:
                verdicts[x["verdict"]] += 1
            rows.append([task, label, len(seeds), mean_std(final), f"{statistics.median(final):.1f}", cost_cell,
                         f"{statistics.fmean(x['search_s'] for x in r):.0f}", f"{statistics.fmean(x['llm_s'] for x in r):.0f}",
                         f"{statistics.median(x['gap_s'] for x in r):.2f}", ", ".join(f"{k} {n}" for k, n in sorted(verdicts.items()))])
        cost = (means["pp"] - means["pp-hardened"]) / abs(means["pp"])
        n_seeds = f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''}"
        targets.append((f"{task}: pp-hardened with pacing costs at most {TARGET:.0%} of pp's mean final return",
                        f"{cost:+.1%} ({means['pp-hardened']:.1f} vs {means['pp']:.1f}, {n_seeds}{_interval(data, task, cost)})",
                        cost <= TARGET))
    n = sum(len(v) for v in data.values())
    source = (f"{n} finished runs of `ppprops experiment benchmarks/hardened.toml` under `{out}`"
              f"{' (reused as recorded, nothing started)' if ctx.collect else ''}; each row holds the seeds finished in both arms")
    body = [f"{source} (2 jobs, one llama.cpp thread each). Final evaluation: mean (std) and median over seeds of the mean return "
            "of 20 fresh episodes of the policy handed over; cost: (pp mean - hardened mean) / |pp mean| (positive: the hardened "
            "arm is worse); seconds are means per run, the gap a median over runs of each run's median time between an answer "
            "and the next request:", "",
            table(["task", "method", "seeds", "final", "median", "quality cost", "search phase (s)", "LLM requests (s)",
                   "answer to next request (s)", "audit"], rows)]
    for text, measured, ok in targets:
        body += ["", f"- {text}: {measured}. Target {'met' if ok else 'NOT met'}."]
    return Section("hardened", "16. pp-hardened with request pacing against pp", "\n".join(body), data, targets=targets)
