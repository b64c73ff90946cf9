"""6. Search quality at an equal budget: pp with the embedded model against random search and CMA-ES.

A grid (``benchmarks/quality.toml``) run with ``ppprops experiment`` on both cores (one llama.cpp
thread per run): CartPole, Acrobot and Pendulum-v1 with ten seeds, Ant-Ultra (D=88) with three,
every method with the same number of evaluated policies (10 random warm-up + 50 proposals); pp
uses the embedded model's default, the document form (``wire.document``). The same grid runs pp
in the paper's chat form on CartPole, for benchmark 1's "no loss in search results". The figure
of merit is the final evaluation: the mean return over 20 fresh episodes of the policy with the
best single-episode return of the search. Every pp run is also audited (``ppprops audit``).
"""

from __future__ import annotations

import shutil
import statistics
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

from _common import Context, Section, llm_calls, mean_std, table, timings

from ppprops.privacy.audit import audit_run
from ppprops.report import run_summary

SPEC = Path(__file__).with_name("quality.toml")
ARMS = (("pp", "PP-ProPS (embedded Gemma 3 270M)"), ("random", "random search"), ("cmaes", "CMA-ES"))
TARGET_TASKS = ("CartPole", "Acrobot", "Pendulum-v1")  # issue 14: above random in mean and median, at least CMA-ES's mean
TASKS = (*TARGET_TASKS, "Ant-Ultra")


def _llm_use(run_dir: Path, summary: dict[str, Any]) -> dict[str, float]:
    """Where the LLM's time went in one run, from llama.cpp's own accounting of every answer."""
    calls = llm_calls(run_dir)
    t = [timings(c["response"]) for c in calls if c["ok"]]
    cached = sum(x.get("cache_n", 0.0) for x in t)
    processed = sum(x.get("prompt_n", 0.0) for x in t)
    counts = summary["counts"]
    return {
        "calls": len(calls),
        "llm_s": sum(c["latency_s"] for c in calls),
        "prefill_s": sum(x.get("prompt_ms", 0.0) for x in t) / 1000,
        "decode_s": sum(x.get("predicted_ms", 0.0) for x in t) / 1000,
        "cached_share": cached / (cached + processed) if cached + processed else 0.0,
        "llm_candidates": counts["llm"],
        "fallback_candidates": counts["fallback"],
        "repeats_refused": counts["answer_failures"].get("repeats_history", 0),
    }


def median_of(values: list[float]) -> str:
    return f"{statistics.median(values):.1f}" if values else "-"


def run(ctx: Context) -> Section:
    out = ctx.out / "quality"
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "ppprops", "experiment", str(SPEC), "--out", str(out), "--quiet"]
    if ctx.quick:
        cmd += ["--seeds", "2", "--warmup", "3", "--iterations", "2", "--final-episodes", "2"]
    subprocess.run(cmd, check=True)
    results: dict[tuple[str, str], dict[str, list[Any]]] = defaultdict(lambda: {"best": [], "final": [], "llm": [], "seeds": []})
    dirs: dict[tuple[str, str, int], Path] = {}
    audits = {"runs": 0, "clean": 0, "not_clean": []}
    for run_dir in sorted(p.parent for p in out.glob("runs/*/run.sqlite")):
        s = run_summary(run_dir)
        arm = s["method"] + ("-chat" if s["config"].get("prompt_form") == "chat" else "")
        r = results[(s["env"], arm)]
        r["best"].append(s["best"]["return"])
        r["final"].append(s["final_eval"]["mean"])
        r["seeds"].append(s["seed"])
        if s["method"] == "pp":
            r["llm"].append(_llm_use(run_dir, s))
            report = audit_run(run_dir)
            audits["runs"] += 1
            audits["clean"] += int(report.clean)
            if not report.clean:
                audits["not_clean"].append(f"{run_dir.name}: {report.verdict()}")
        dirs[(s["env"], arm, s["seed"])] = run_dir
    ctx.cache["cache_cartpole_run"] = dirs.get(("CartPole", "pp-chat", 0))
    ctx.cache["cache_acrobot_run"] = dirs.get(("Acrobot", "pp", 0))
    ctx.cache["doc_cartpole_run"] = dirs.get(("CartPole", "pp", 0))
    rows, data, targets = [], {}, []
    for task in TASKS:
        for arm, label in ARMS:
            r = results.get((task, arm))
            if r is None:
                continue
            data[f"{task}/{arm}"] = r
            rows.append([task, label, len(r["final"]), mean_std(r["final"]), median_of(r["final"]), mean_std(r["best"])])
    body = [f"{sum(len(r['final']) for r in results.values())} runs from `ppprops experiment benchmarks/quality.toml` "
            "(2 jobs, one llama.cpp thread each); final evaluation: mean (std) and median over seeds of the mean return of "
            "20 fresh episodes of each run's best policy:", "",
            table(["task", "method", "seeds", "final-evaluation return", "median", "best return in the search"], rows), ""]
    for task in TARGET_TASKS:
        pp, rnd, cma = (results.get((task, a)) for a in ("pp", "random", "cmaes"))
        if not (pp and rnd and cma):
            continue
        m = statistics.fmean
        met = (m(pp["final"]) > m(rnd["final"]) and statistics.median(pp["final"]) > statistics.median(rnd["final"])
               and m(pp["final"]) >= m(cma["final"]))
        targets.append((f"{task}: PP-ProPS above random (mean and median) and at least CMA-ES (mean), final-evaluation return",
                        f"mean {m(pp['final']):.1f} vs {m(rnd['final']):.1f} vs {m(cma['final']):.1f}; median "
                        f"{statistics.median(pp['final']):.1f} vs {statistics.median(rnd['final']):.1f}", met))
        body.append(f"- {task}: PP-ProPS mean {m(pp['final']):.1f}, median {statistics.median(pp['final']):.1f}; random search "
                    f"mean {m(rnd['final']):.1f}, median {statistics.median(rnd['final']):.1f}; CMA-ES mean {m(cma['final']):.1f}. "
                    f"Target {'met' if met else 'NOT met'}.")
    ant = [results.get(("Ant-Ultra", a)) for a, _ in ARMS]
    if all(ant):
        targets.append(("Ant-Ultra (D=88), 3 seeds: PP-ProPS vs random vs CMA-ES, final-evaluation return",
                        " vs ".join(mean_std(r["final"]) for r in ant if r), None))
    # what the LLM did and where its time went
    use_rows = []
    for task in TASKS:
        for arm in ("pp", "pp-chat"):
            r = results.get((task, arm))
            if not r or not r["llm"]:
                continue
            u = r["llm"]
            tot = sum(x["llm_s"] for x in u)
            pre, dec = sum(x["prefill_s"] for x in u), sum(x["decode_s"] for x in u)
            use_rows.append([task, "document (default)" if arm == "pp" else "chat", sum(x["llm_candidates"] for x in u),
                             sum(x["fallback_candidates"] for x in u), sum(x["repeats_refused"] for x in u), sum(x["calls"] for x in u),
                             f"{tot / max(1, sum(x['calls'] for x in u)):.2f}",
                             f"{100 * pre / tot:.0f}% / {100 * dec / tot:.0f}%" if tot else "-",
                             f"{100 * statistics.fmean(x['cached_share'] for x in u):.0f}%"])
    body += ["", "What the model did in the pp runs (all seeds together) and where the LLM time went (llama.cpp's own timings):", "",
             table(["task", "prompt form", "LLM candidates", "fallback candidates", "answers refused as a history repeat",
                    "requests", "mean request (s)", "prefill / decoding share of request time", "prompt tokens from the cache"],
                   use_rows)]
    chat, doc = results.get(("CartPole", "pp-chat")), results.get(("CartPole", "pp"))
    if chat and doc:
        ctx.cache["quality_forms"] = [["document (default for the embedded model)", mean_std(doc["best"]), mean_std(doc["final"]),
                                       median_of(doc["final"])],
                                      ["chat (the paper's prompt, list form)", mean_std(chat["best"]), mean_std(chat["final"]),
                                       median_of(chat["final"])]]
    data["audits"] = audits
    body += ["", f"- `ppprops audit`: {audits['clean']} of {audits['runs']} pp runs clean."
             + ("" if not audits["not_clean"] else " Not clean: " + "; ".join(audits["not_clean"]))]
    targets.append(("`ppprops audit` clean on every pp run of the benchmark", f"{audits['clean']} of {audits['runs']}",
                    audits["clean"] == audits["runs"]))
    return Section("quality", "6. Search quality at an equal budget", "\n".join(body), data, targets=targets)
