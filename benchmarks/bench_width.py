"""15. Search quality at width P: P = 1 against P = 4, at equal candidates and at equal rounds.

pp with the embedded model (document form, decimal numbers) on CartPole, Pendulum-v1 and Acrobot,
10 warm-up + 50 LLM candidates, the selection stage and a final evaluation on 20 fresh episodes;
random search and CMA-ES beside it at the same budget and width. At P = 4 the LLM phase proposes
four candidates per round from one shown history (four concurrent requests, four slots on the
embedded server), so the same 50 candidates take 13 rounds; at equal rounds P = 4 gets 50 rounds,
200 candidates, which is what a user with a concurrent endpoint pays the same wall time for.

Every run at P = 4 shares the secrets of the same method's run at P = 1 with the same seed (the
same warm-up, A and c, and the same keyed draws), so a row compares the width alone. The P = 1 pp runs have the settings of benchmark 12's
decimal arm: ``--keep`` reuses such a run when it is copied under ``--out``/width (a finished run
counts by its policy file). ``--keep --collect`` starts nothing and reports the (task, seed) pairs
whose runs have all finished; the rows say how many seeds each holds.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

from _common import Context, Section, config, finished, llm_calls, run_search, run_secrets, table

from ppprops.store import open_store
from ppprops.summary import run_summary

TASKS = ("CartPole", "Pendulum-v1", "Acrobot")
SEEDS = (0, 1, 2, 3, 4)
ITERATIONS = 50
WIDE = 4
# (arm, method, P, LLM candidates): equal candidates for every method; equal rounds for pp only
ARMS = (("pp-P1", "pp", 1, ITERATIONS), ("pp-P4", "pp", WIDE, ITERATIONS), ("pp-P4-rounds", "pp", WIDE, WIDE * ITERATIONS),
        ("random-P1", "random", 1, ITERATIONS), ("random-P4", "random", WIDE, ITERATIONS),
        ("cmaes-P1", "cmaes", 1, ITERATIONS), ("cmaes-P4", "cmaes", WIDE, ITERATIONS))
LABELS = {"pp-P1": "pp, P = 1", "pp-P4": "pp, P = 4", "pp-P4-rounds": f"pp, P = 4, {ITERATIONS} rounds",
          "random-P1": "random, P = 1", "random-P4": "random, P = 4", "cmaes-P1": "CMA-ES, P = 1", "cmaes-P4": "CMA-ES, P = 4"}
# the order runs are started in (a partial run still fills whole rows): equal candidates on every
# task, cheapest first, then equal rounds (four times a row's LLM time, so on Pendulum-v1 alone)
EQUAL = tuple(a for a, *_ in ARMS if a != "pp-P4-rounds")
PLAN = ((("CartPole", "Pendulum-v1"), EQUAL), (("Acrobot",), EQUAL), (("Pendulum-v1",), ("pp-P4-rounds",)))



def _measure(run_dir: Path) -> dict[str, Any]:
    s = run_summary(run_dir)
    calls = llm_calls(run_dir)
    src = s["counts"]["by_source"]
    with open_store(run_dir) as store:
        times = store.candidate_times()
    warm = [t[3] for t in times if t[1] == "warmup"]
    search = [t[3] for t in times if t[1] not in ("warmup", "reeval")]
    return {"final": s["final_eval"]["mean"], "best": (s["best"].get("search_best") or s["best"])["return"],
            "requests": len(calls), "phase_s": search[-1] - warm[-1] if search and warm else 0.0,
            "candidates": sum(n for k, n in src.items() if k not in ("warmup", "reeval"))}


def run(ctx: Context) -> Section:
    arms = {arm: (method, width, n) for arm, method, width, n in ARMS}
    data: dict[str, dict[str, Any]] = {}
    done: dict[tuple[str, str], list[int]] = {}
    for tasks, names in PLAN:
        for task in tasks:
            for seed in SEEDS[:1] if ctx.quick else SEEDS:
                if ctx.collect and not all(finished(ctx.dir("width") / f"{task}-{seed}-{arm}") for arm in names):
                    continue  # a seed counts in every row of its group or in none, so the rows compare the same seeds
                for arm in names:
                    method, width, n = arms[arm]
                    run_dir = ctx.dir("width") / f"{task}-{seed}-{arm}"
                    if not finished(run_dir):
                        first = f"{method}-P1"
                        shared = ctx.dir("width") / f"{task}-{seed}-{first}" if arm != first else None
                        if ctx.collect or (shared is not None and not finished(shared)):
                            continue
                        budget = n if not ctx.quick else 2 * width  # --quick: the smallest budget each width accepts
                        cfg = config(task, method, warmup=10, iterations=budget, seed=seed, final_episodes=20,
                                     number_format="decimal", parallel=width)
                        run_search(cfg, run_dir, secrets=None if shared is None else run_secrets(shared))
                    data[f"{task}/{seed}/{arm}"] = _measure(run_dir)
                    done.setdefault((task, arm), []).append(seed)
    rows = []
    for task in TASKS:
        for arm in arms:
            seeds = done.get((task, arm), [])
            if not seeds:
                continue
            runs = [data[f"{task}/{s}/{arm}"] for s in seeds]
            finals = [r["final"] for r in runs]
            req = sum(r["requests"] for r in runs)
            rows.append([task, LABELS[arm], len(runs), f"{statistics.fmean(finals):.1f}", f"{statistics.median(finals):.1f}",
                         f"{statistics.fmean(r['best'] for r in runs):.1f}", round(statistics.fmean(r["candidates"] for r in runs)),
                         req, f"{statistics.fmean(r['phase_s'] for r in runs) / 60:.1f}"])
    body = [
        "pp: embedded Gemma 3 270M, document form, decimal numbers; 10 warm-up + LLM candidates as the row says, selection stage "
        "(top 5 on 10 fresh episodes), final evaluation on 20 fresh episodes. A row at P = 4 shares each seed's secrets "
        "with the same method's P = 1 row. "
        "The search phase is the wall time from the last warm-up candidate to the last search candidate, averaged over the seeds "
        "(LLM requests and episodes; shared cores, see the header's load).",
        "",
        table(["task", "arm", "seeds", "final-evaluation mean", "median", "best search return", "LLM candidates",
               "LLM requests (all seeds)", "search phase (min per run)"], rows),
        "",
    ]
    for task in TASKS:
        per_seed = {arm: [data[f"{task}/{sd}/{arm}"]["final"] for sd in done.get((task, arm), [])]
                    for arm in ("pp-P1", "pp-P4", "pp-P4-rounds")}
        if per_seed["pp-P1"] and per_seed["pp-P4"]:
            body.append(f"- {task}, pp final-evaluation mean per seed: " + "; ".join(
                f"{LABELS[arm]}: {' / '.join(f'{v:.1f}' for v in vals)}" for arm, vals in per_seed.items() if vals) + ".")
    return Section("width", "15. Search quality at width P (equal candidates, equal rounds)", "\n".join(body),
                   {"runs": data})
