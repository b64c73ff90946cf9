"""6. Search quality at an equal budget: pp with the embedded model against random search and CMA-ES.

A grid (``benchmarks/quality.toml``) of CartPole and Acrobot runs, five seeds each, every method
with the same number of evaluated policies (10 random warm-up + 15 proposals), run with
``ppprops experiment`` on both cores. Best return is the best single-episode return seen during
the search; the final evaluation is the mean over 20 fresh episodes of that best policy.
The same grid runs pp with the ProPS parameter form, for benchmark 1.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

from _common import Context, Section, mean_std, table

from ppprops.report import run_summary

SPEC = Path(__file__).with_name("quality.toml")
ARMS = (("pp", "PP-ProPS (embedded Gemma 3 270M)"), ("random", "random search"), ("cmaes", "CMA-ES"))


def run(ctx: Context) -> Section:
    out = ctx.out / "quality"
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "ppprops", "experiment", str(SPEC), "--out", str(out), "--quiet"]
    if ctx.quick:
        cmd += ["--seeds", "2", "--warmup", "3", "--iterations", "2", "--final-episodes", "2"]
    subprocess.run(cmd, check=True)
    results: dict[tuple[str, str], dict[str, list[float]]] = defaultdict(lambda: {"best": [], "final": []})
    dirs: dict[tuple[str, str, int], Path] = {}
    for run_dir in sorted(p.parent for p in out.glob("runs/*/run.sqlite")):
        s = run_summary(run_dir)
        arm = s["method"] + ("-propsform" if s["config"].get("prompt_params") == "indexed" else "")
        results[(s["env"], arm)]["best"].append(s["best"]["return"])
        results[(s["env"], arm)]["final"].append(s["final_eval"]["mean"])
        dirs[(s["env"], arm, s["seed"])] = run_dir
    ctx.cache["cache_cartpole_run"] = dirs.get(("CartPole", "pp", 0))
    ctx.cache["cache_acrobot_run"] = dirs.get(("Acrobot", "pp", 0))
    rows, data = [], {}
    for task in ("CartPole", "Acrobot"):
        for arm, label in ARMS:
            r = results.get((task, arm))
            if r is None:
                continue
            data[f"{task}/{arm}"] = r
            rows.append([task, label, len(r["best"]), mean_std(r["best"]), mean_std(r["final"])])
    forms = [("list (default)", "pp"), ("ProPS `params[i]: v`", "pp-propsform")]
    ctx.cache["quality_forms"] = [[name, mean_std(results[("CartPole", arm)]["best"]), mean_std(results[("CartPole", arm)]["final"])]
                                  for name, arm in forms if ("CartPole", arm) in results]
    data["CartPole/pp-propsform"] = results.get(("CartPole", "pp-propsform"))
    n = sum(len(r["best"]) for r in results.values())
    body = [f"{n} runs from `ppprops experiment benchmarks/quality.toml` (2 jobs, one llama.cpp thread each); mean (std) over seeds:", "",
            table(["task", "method", "seeds", "best return", "final-evaluation return (20 episodes)"], rows)]
    targets = [(f"{task}: PP-ProPS vs random vs CMA-ES, final-evaluation return",
                " vs ".join(mean_std(results[(task, arm)]["final"]) for arm, _ in ARMS if (task, arm) in results), None)
               for task in ("CartPole", "Acrobot")]
    return Section("quality", "6. Search quality at an equal budget", "\n".join(body), data, targets=targets)
