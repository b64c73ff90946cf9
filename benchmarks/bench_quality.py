"""6. Search quality at an equal budget: pp with the embedded model against random search and CMA-ES.

A grid (``benchmarks/quality.toml``) run with ``ppprops experiment`` on both cores (one llama.cpp
thread per run): CartPole, Acrobot and Pendulum-v1 with ten seeds, Ant-Ultra (D=88) with three,
every method with the same number of evaluated policies (10 random warm-up + 50 proposals) and
the same selection stage (the top 5 candidates of the search re-run on 10 fresh episodes each, the
best pooled mean handed over: ``proposers.selection``); pp uses the embedded model's default, the
document form (``wire.document``). The grid also runs pp without its exploration rule on
CartPole (``--explore off``), the rule's ablation. (The paper's chat form is reported when a grid
holds it, as earlier rounds' did; this spec leaves it out for time.) The figure of merit is the final evaluation: the mean return over 20
fresh episodes of the policy handed over. The old selection (the best single search return, as
before the selection stage) is evaluated on the same 20 episodes for every run, so both stand side by side.
Every pp run is also audited (``ppprops audit``).

With ``run_all.py --keep`` a grid already recorded under ``--out`` is reused: ``ppprops
experiment`` skips its finished runs and resumes the rest. With ``--keep --collect`` nothing is
started: only the runs the grid has finished are reported (for a grid still running in another
process), and every row says how many seeds it holds.
"""

from __future__ import annotations

import statistics
import subprocess
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from _common import Context, Section, grid_dir, llm_calls, mean_std, table, timings

from ppprops import seeding
from ppprops.config import RunConfig
from ppprops.evaluation import Evaluator
from ppprops.loop import best_candidate, search_candidates
from ppprops.privacy.audit import audit_run
from ppprops.store import open_store
from ppprops.summary import run_summary

SPEC = Path(__file__).with_name("quality.toml")
ARMS = (("pp", "PP-ProPS (embedded Gemma 3 270M)"), ("random", "random search"), ("cmaes", "CMA-ES"))
TARGET_TASKS = ("CartPole", "Acrobot", "Pendulum-v1")  # above random in mean and median, at least CMA-ES's mean
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


def _steps(run_dir: Path, warmup: int) -> dict[str, float]:
    """How far the search-phase proposals go from the best policy found before them, and how often
    they beat it: the median RMS per coordinate of theta - theta_best (raw units; the box is 12
    wide), and the number of new bests after the warm-up."""
    with open_store(run_dir) as store:
        cands = store.candidates()
    P = np.array([c.params for c in cands], dtype=np.float64)
    R = np.array([c.ret for c in cands], dtype=np.float64)
    steps = [float(np.linalg.norm(P[i] - P[int(np.argmax(R[:i]))]) / np.sqrt(P.shape[1])) for i in range(warmup, len(R))]
    return {"step": statistics.median(steps) if steps else float("nan"),
            "new_bests": float(sum(R[i] > R[:i].max() for i in range(warmup, len(R))))}


def old_selection_final(run_dir: Path) -> float | None:
    """The final evaluation the run would have had without the selection stage: the candidate with the best single
    search return, on the same fresh episodes as the run's own final evaluation (the same seeds)."""
    with open_store(run_dir) as store:
        cands, fe, config = store.candidates(), store.final_eval(), RunConfig.from_json(store.config())
    if fe is None or not fe.returns:
        return None
    old = best_candidate(search_candidates(cands))
    if old.index == fe.candidate_index:
        return fe.mean
    with Evaluator(config.make_task()) as ev:
        seeds = list(fe.seeds) or seeding.final_eval_seeds(config.seed, len(fe.returns))
        return float(np.mean(ev.evaluate(old.params, seeds).episode_returns))


def median_of(values: list[float]) -> str:
    return f"{statistics.median(values):.1f}" if values else "-"


def run(ctx: Context) -> Section:
    out, cmd, reused = grid_dir(ctx, "quality", SPEC)
    if ctx.quick:
        cmd += ["--seeds", "1", "--tasks", "CartPole,Acrobot", "--warmup", "3", "--iterations", "2", "--final-episodes", "1"]
    if not ctx.collect:
        subprocess.run(cmd, check=True)
    results: dict[tuple[str, str], dict[str, list[Any]]] = defaultdict(
        lambda: {"best": [], "final": [], "old_final": [], "llm": [], "seeds": [], "steps": [], "episodes": []})
    dirs: dict[tuple[str, str, int], Path] = {}
    audits: dict[str, Any] = {"runs": 0, "clean": 0, "not_clean": [], "verdicts": defaultdict(int)}
    unfinished = []
    for run_dir in sorted(p.parent for p in out.glob("runs/*/run.sqlite")):
        s = run_summary(run_dir)
        if s["status"] != "finished" or not s.get("final_eval"):
            unfinished.append(run_dir.name)  # still running (or stopped): no final evaluation to report
            continue
        arm = s["method"] + ("-chat" if s["config"].get("prompt_form") == "chat" else "")
        if s["config"].get("explore") is False:
            arm += "-noexplore"
        r = results[(s["env"], arm)]
        r["best"].append((s["best"].get("search_best") or s["best"])["return"])
        r["final"].append(s["final_eval"]["mean"])
        r["old_final"].append(old_selection_final(run_dir))
        r["episodes"].append(s["counts"].get("episodes", {}))
        r["seeds"].append(s["seed"])
        r["steps"].append(_steps(run_dir, int(s["config"].get("warmup", 10))))
        if s["method"] == "pp":
            r["llm"].append(_llm_use(run_dir, s))
            report = audit_run(run_dir)
            audits["runs"] += 1
            audits["clean"] += int(report.clean)
            audits["verdicts"][report.verdict().split(":")[0]] += 1
            if report.leaks or report.unverified:
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
            old = [x for x in r["old_final"] if x is not None]
            rows.append([task, label, len(r["final"]), mean_std(r["final"]), median_of(r["final"]), mean_std(old), median_of(old),
                         mean_std(r["best"])])
    n_runs = sum(len(r["final"]) for r in results.values())
    if not reused:
        source = f"{n_runs} runs from `ppprops experiment benchmarks/quality.toml`"
    elif ctx.collect:
        source = (f"{n_runs} finished runs of the grid recorded under `{out}` (reused as recorded, nothing started: "
                  f"{len(unfinished)} unfinished run(s) left out{', and runs not started yet are missing' if unfinished else ''}; "
                  "the seeds column says how many each row holds)")
    else:
        source = f"{n_runs} runs of the grid recorded under `{out}` (reused: finished runs kept, the rest resumed)"
    body = [f"{source} (2 jobs, one llama.cpp thread each); final evaluation: mean (std) and median over seeds of the mean "
            "return of 20 fresh episodes of the policy handed over, with the selection stage (new) and, on the same 20 episodes, "
            "the candidate with the best single search return (old, without the selection stage):", "",
            table(["task", "method", "seeds", "final (new selection)", "median", "final (old selection)", "median",
                   "best single return in the search"], rows), ""]
    ep_rows = []
    for task in TASKS:
        for arm, label in ARMS:
            r = results.get((task, arm))
            if r and r["episodes"]:
                e = r["episodes"]
                ep_rows.append([task, label, f"{statistics.fmean(x.get('search', 0) for x in e):.0f}",
                                f"{statistics.fmean(x.get('selection', 0) for x in e):.0f}", f"{statistics.fmean(x.get('final', 0) for x in e):.0f}"])
    body += ["Episodes per run (means over seeds): the selection stage's cost beside the search's; the LLM budget is the same "
             "(one proposal per LLM call):", "", table(["task", "method", "search", "selection stage", "final evaluation"], ep_rows), ""]
    for task in TARGET_TASKS:
        pp, rnd, cma = (results.get((task, a)) for a in ("pp", "random", "cmaes"))
        if not (pp and rnd and cma):
            continue
        m = statistics.fmean
        met = (m(pp["final"]) > m(rnd["final"]) and statistics.median(pp["final"]) > statistics.median(rnd["final"])
               and m(pp["final"]) >= m(cma["final"]))
        seeds = f" ({len(pp['final'])}/{len(rnd['final'])}/{len(cma['final'])} seeds)"
        targets.append((f"{task}: PP-ProPS above random (mean and median) and at least CMA-ES (mean), final-evaluation return (new selection)",
                        f"mean {m(pp['final']):.1f} vs {m(rnd['final']):.1f} vs {m(cma['final']):.1f}; median "
                        f"{statistics.median(pp['final']):.1f} vs {statistics.median(rnd['final']):.1f}"
                        + (seeds if ctx.collect else ""), met))
        body.append(f"- {task}: PP-ProPS mean {m(pp['final']):.1f}, median {statistics.median(pp['final']):.1f}; random search "
                    f"mean {m(rnd['final']):.1f}, median {statistics.median(rnd['final']):.1f}; CMA-ES mean {m(cma['final']):.1f}. "
                    f"Target {'met' if met else 'NOT met'}.")
    ant = [results.get(("Ant-Ultra", a)) for a, _ in ARMS]
    if all(ant):
        targets.append(("Ant-Ultra (D=88), 3 seeds: PP-ProPS vs random vs CMA-ES, final-evaluation return",
                        " vs ".join(mean_std(r["final"]) for r in ant if r)
                        + (f" ({'/'.join(str(len(r['final'])) for r in ant if r)} seeds)" if ctx.collect else ""), None))
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
    step_rows = []
    for task in TASKS:
        for arm, label in (*ARMS[:1], ("pp-chat", "PP-ProPS, chat form"), *ARMS[1:]):
            r = results.get((task, arm))
            if r and r["steps"]:
                step_rows.append([task, label, len(r["steps"]), f"{statistics.median(x['step'] for x in r['steps']):.2f}",
                                  f"{statistics.fmean(x['new_bests'] for x in r['steps']):.1f}"])
    body += ["", "How far each method's proposals go from the best policy found before them (search phase only; raw "
             "parameters, RMS per coordinate, the box [-6, 6] is 12 wide), and how often a proposal beats it:", "",
             table(["task", "method", "seeds", "median step from the best so far", "new bests per run"], step_rows)]
    ablation = []
    for task in TARGET_TASKS:
        on, off = results.get((task, "pp")), results.get((task, "pp-noexplore"))
        if on and off:
            for label, r in (("exploration when stuck (default)", on), ("no exploration (--explore off)", off)):
                ablation.append([task, label, len(r["final"]), mean_std(r["final"]), median_of(r["final"]), mean_std(r["best"]),
                                 f"{statistics.median(x['step'] for x in r['steps']):.2f}",
                                 f"{statistics.fmean(x['new_bests'] for x in r['steps']):.1f}"])
    if ablation:
        body += ["", "The exploration rule alone (pp, document form; the same seeds and selection stage; after 3 LLM iterations "
                 "without a new best shown return an iteration is sampled at temperature 2.0, untruncated):", "",
                 table(["task", "pp", "seeds", "final (new selection)", "median", "best single return", "median step from the best",
                        "new bests per run"], ablation)]
    forms = []
    for task in TARGET_TASKS:
        chat, doc = results.get((task, "pp-chat")), results.get((task, "pp"))
        if chat and doc:
            forms.append([task, "document (default for the embedded model)", len(doc["final"]), mean_std(doc["best"]),
                          mean_std(doc["final"]), median_of(doc["final"])])
            forms.append([task, "chat (the paper's prompt, list form)", len(chat["final"]), mean_std(chat["best"]),
                          mean_std(chat["final"]), median_of(chat["final"])])
    if forms:
        ctx.cache["quality_forms"] = forms
    audits["verdicts"] = dict(audits["verdicts"])
    data["audits"] = audits
    data["unfinished"] = unfinished
    verdicts = ", ".join(f"{v} {n}" for v, n in sorted(audits["verdicts"].items()))
    sent_ok = audits["runs"] - len(audits["not_clean"])
    body += ["", f"- `ppprops audit` on the {audits['runs']} pp runs: {verdicts or 'none'}. "
             f"{sent_ok} of {audits['runs']} sent no raw value and nothing the audit cannot account for"
             + ("." if not audits["not_clean"] else "; not: " + "; ".join(audits["not_clean"]) + ".")
             + (" EXPOSED is the verdict on the channels the paper's scheme keeps under `pp` (integer-return lattice, "
                "diagnostics, caps, clipping at the box edge; docs/threat-model.md), which only `pp-hardened` closes; the prompt form "
                "changes none of them." if audits["verdicts"].get("EXPOSED") else "")]
    targets.append(("`ppprops audit` on every pp run: no raw value sent, nothing unaccounted for (LEAK/UNVERIFIED)",
                    f"{sent_ok} of {audits['runs']} ({verdicts or 'no runs'})", sent_ok == audits["runs"] and audits["runs"] > 0))
    return Section("quality", "6. Search quality at an equal budget", "\n".join(body), data, targets=targets)
