"""10. Nonlinear policies: the linear policy against small MLPs (``--policy mlp:8``, ``mlp:16``).

Every arm searches the same task at the same budget (``--warmup`` random warm-up + ``--iterations``
proposals, the default selection stage, 20 fresh final episodes): random search and CMA-ES on the
same parameters as pp, so the comparison is fair. pp talks to the embedded model (Gemma 3 270M,
its default document form); run it under the shared model lock::

    python benchmarks/bench_mlp.py --methods random,cmaes --tasks Pendulum-v1,CartPole --seeds 0,1,2,3,4 --out /tmp/mlp-bench
    flock /work/llm.lock python benchmarks/bench_mlp.py --methods pp --tasks Pendulum-v1 --seeds 0,1 --iterations 20 --out /tmp/mlp-bench

Each run lands in ``OUT/<task>-<method>-<policy>-s<seed>`` (a finished one is reused); ``--report``
prints the tables of every run under ``OUT``: final-evaluation mean (std) and median over seeds per
(task, method, policy), and, for the pp runs, the answer's tokens per parameter and the request time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

POLICIES = ("linear", "mlp:8", "mlp:16")


def _run(out: Path, task: str, method: str, policy: str, seed: int, warmup: int, iterations: int, episodes: int = 1) -> None:
    import ppprops

    run_dir = out / f"{task}-{method}-{policy.replace(':', '')}{f'-e{episodes}' if episodes != 1 else ''}-s{seed}"
    if (run_dir / "best_policy.json").exists():
        return
    if run_dir.exists():
        import shutil

        shutil.rmtree(run_dir)
    t0 = time.perf_counter()
    r = ppprops.search(task, method=method, policy=policy, warmup=warmup, iterations=iterations, seed=seed, out=run_dir,
                       evaluation={"final_episodes": 20, "episodes": episodes})
    assert r.final is not None
    print(f"{run_dir.name}: final {r.final.mean:.1f} in {time.perf_counter() - t0:.0f} s", flush=True)


def _report(out: Path) -> None:
    from ppprops import load_run
    from ppprops.store import open_store

    finals: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    budget: dict[tuple[str, str, str], str] = {}
    tokens: dict[tuple[str, str], list[tuple[int, float, float, float]]] = defaultdict(list)
    for run_dir in sorted(p for p in out.iterdir() if (p / "best_policy.json").exists()):
        r = load_run(run_dir)
        doc = json.loads((run_dir / "best_policy.json").read_text())
        policy = "linear" if doc["format"].startswith("ppprops.linear") else "mlp:" + ",".join(map(str, doc["policy"]["hidden"]))
        episodes = f", {r.config.episodes} episodes each" if r.config.episodes != 1 else ""
        key = (r.task, r.method, policy + episodes)
        assert r.final is not None
        finals[key].append(r.final.mean)
        budget[key] = f"{r.config.warmup}+{r.config.iterations}"
        if r.method == "pp":
            with open_store(run_dir) as store:
                calls = store.llm_calls()
            D = len(doc["theta"])
            for c in calls:
                if c["ok"] and c["completion_tokens"]:
                    tokens[(r.task, policy)].append((D, float(c["prompt_tokens"] or 0), float(c["completion_tokens"]),
                                                     float(c["latency_s"])))  # fmt: skip
    print("| task | method | policy | budget | seeds | final mean (std) | median |")
    print("|---|---|---|---|---|---|---|")
    for key in sorted(finals, key=lambda k: (k[0], k[1], POLICIES.index(k[2].split(",")[0]), k[2])):
        v = finals[key]
        print(f"| {key[0]} | {key[1]} | {key[2]} | {budget[key]} | {len(v)} | {statistics.fmean(v):.1f} ({statistics.pstdev(v):.1f}) | "
              f"{statistics.median(v):.1f} |")
    if tokens:
        print()
        print("| task | policy | D | requests | prompt tokens (mean) | answer tokens (mean) | answer tokens per parameter | mean request (s) |")
        print("|---|---|---|---|---|---|---|---|")
        for (task, policy), rows in sorted(tokens.items()):
            D = rows[0][0]
            p, a, s = (statistics.fmean(r[i] for r in rows) for i in (1, 2, 3))
            print(f"| {task} | {policy} | {D} | {len(rows)} | {p:.0f} | {a:.0f} | {a / D:.2f} | {s:.1f} |")


def _prompt_sizes(out: Path, tasks: list[str], policies: list[str]) -> None:
    """Prompt size against D with no model: each form's request after the 10-entry warm-up, answered by
    the offline stand-in (``EchoOptimizer``); the answer's token budget is the form's (``answer_budget``)."""
    import ppprops
    from ppprops.llm.settings import LLMConfig
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.store import open_store

    print("| task | policy | D | form | prompt characters | characters per parameter | answer budget (tokens) | budget per parameter |")
    print("|---|---|---|---|---|---|---|---|")
    for task in tasks:
        for policy in policies:
            for form in ("chat", "document"):
                run_dir = out / f"prompt-{task}-{policy.replace(':', '')}-{form}"
                if not run_dir.exists():
                    ppprops.search(task, method="pp", policy=policy, warmup=10, iterations=1, seed=0, out=run_dir,
                                   llm=EchoOptimizer(LLMConfig(), spread=0.5), prompt={"form": form},
                                   evaluation={"final_episodes": 1, "select_top": 0})  # fmt: skip
                with open_store(run_dir) as store:
                    call = store.llm_calls()[0]
                body = json.loads(call["request"])
                D = len(json.loads((run_dir / "best_policy.json").read_text())["theta"])
                budget = int(body.get("max_tokens") or 0)
                print(f"| {task} | {policy} | {D} | {form} | {call['prompt_chars']} | {call['prompt_chars'] / D:.0f} | {budget} | "
                      f"{budget / D:.1f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--tasks", default="Pendulum-v1,CartPole")
    ap.add_argument("--methods", default="random,cmaes")
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--episodes", type=int, default=1, help="episodes per candidate (runs with more than 1 are named -e<N>)")
    ap.add_argument("--report", action="store_true", help="only print the tables of the runs under --out")
    ap.add_argument("--prompt-sizes", action="store_true", help="only measure prompt size against D (no model: the offline stand-in)")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    if a.prompt_sizes:
        _prompt_sizes(a.out, a.tasks.split(","), a.policies.split(","))
        return 0
    if not a.report:
        for task in a.tasks.split(","):
            for method in a.methods.split(","):
                for policy in a.policies.split(","):
                    for seed in (int(s) for s in a.seeds.split(",")):
                        _run(a.out, task, method, policy, seed, a.warmup, a.iterations, a.episodes)
    _report(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
