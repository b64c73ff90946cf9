"""Evaluator throughput against a bare ``env.step`` loop running the same linear policy.

    python benchmarks/bench_eval.py [--tasks Ant-Torso Humanoid-Torso] [--episodes 10] [--rounds 5]

For each task, in one run and interleaved round by round (so load changes hit all three alike), it
measures env steps per second of: a bare loop (reset, policy, step; nothing else), the Evaluator with
one worker (observation adapter, finiteness checks, feedback recording, aggregation) and the
Evaluator with two worker processes (pool already started). It prints the best round of each and the
ratios to the bare loop. Targets: >= 0.9 with one worker, >= 1.7 with two (on a 2-core machine).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from typing import Any

import numpy as np

from ppprops.evaluation import Evaluator, make_policy
from ppprops.tasks import get_task
from ppprops.tasks.base import Task


def bare_loop(task: Task, env: Any, theta: np.ndarray, seeds: list[int]) -> int:
    """The least a rollout can do: no adapter, no checks, no recording. Returns the steps taken."""
    policy = make_policy(task, theta, env)
    idx = None if task.observation.indices is None else list(task.observation.indices)  # type: ignore[attr-defined]
    steps = 0
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        while True:
            s = obs if idx is None else obs[idx]
            obs, _, terminated, truncated, _ = env.step(policy.act(s))
            steps += 1
            if terminated or truncated:
                break
    return steps


def timed(fn: Any) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def bench(name: str, episodes: int, rounds: int, min_steps: int) -> dict[str, float]:
    task = get_task(name)
    # A small fixed policy: deterministic, keeps the robot alive for a while, costs what any theta costs.
    theta = np.random.default_rng(0).uniform(-0.05, 0.05, task.D)
    env = task.make_env()
    # Short episodes (a humanoid falls in ~30 steps) need more of them for a measurable run.
    per_episode = bare_loop(task, env, theta, [0, 1]) / 2
    episodes = max(episodes, math.ceil(min_steps / per_episode))
    seeds = list(range(episodes + episodes % 2))
    best = {"bare": 0.0, "w1": 0.0, "w2": 0.0}
    with Evaluator(task, workers=1) as one, Evaluator(task, workers=2) as two:
        two.evaluate(theta, seeds[:2])  # start the pool and its envs outside the timing
        one.evaluate(theta, seeds[:1])
        for _ in range(rounds):
            dt, steps = timed(lambda: bare_loop(task, env, theta, seeds))
            best["bare"] = max(best["bare"], steps / dt)
            for key, ev in (("w1", one), ("w2", two)):
                dt, fb = timed(lambda ev=ev: ev.evaluate(theta, seeds))
                n = round(float(fb.diagnostics["episode_length"]) * len(seeds))
                if n != steps:
                    raise AssertionError(f"{name}: evaluator ran {n} steps, bare loop {steps}")
                best[key] = max(best[key], n / dt)
    env.close()
    best["steps"] = float(steps)
    best["episodes"] = float(len(seeds))
    return best


def run(ctx):  # type: ignore[no-untyped-def]  # the suite's entry point (run_all.py)
    from _common import Section, table

    tasks, rounds, min_steps = (["Ant-Torso"], 1, 1000) if ctx.quick else (["Ant-Torso", "Humanoid-Torso"], 5, 10000)
    rows, data = [], {}
    for name in tasks:
        r = bench(name, 10, rounds, min_steps)
        data[name] = {**r, "w1_over_bare": r["w1"] / r["bare"], "w2_over_bare": r["w2"] / r["bare"]}
        rows.append([name, int(r["episodes"]), int(r["steps"]), f"{r['bare']:.0f}", f"{r['w1']:.0f}", f"{r['w2']:.0f}",
                     f"{r['w1'] / r['bare']:.2f}", f"{r['w2'] / r['bare']:.2f}"])
    body = [f"Env steps per second, best of {rounds} interleaved rounds; the same policy and seeds in all three:", "",
            table(["task", "episodes", "steps", "bare env.step loop", "Evaluator, 1 worker", "Evaluator, 2 workers",
                   "1 worker / bare", "2 workers / bare"], rows), "",
            "- Targets: at least 0.9 with one worker (the evaluator's own cost) and 1.7 with two on a 2-core machine; "
            "two workers only help when both cores are free."]
    targets = [(f"{name}: 1 worker >= 0.9x, 2 workers >= 1.7x a bare loop", f"{v['w1_over_bare']:.2f}x, {v['w2_over_bare']:.2f}x",
                v["w1_over_bare"] >= 0.9 and v["w2_over_bare"] >= 1.7) for name, v in data.items()]
    return Section("eval", "5. Evaluation throughput", "\n".join(body), data, targets=targets)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=["Ant-Torso", "Humanoid-Torso"])
    p.add_argument("--episodes", type=int, default=10, help="episodes per measurement (even keeps two workers balanced)")
    p.add_argument("--rounds", type=int, default=5, help="interleaved rounds; the best of each is reported")
    p.add_argument("--min-steps", type=int, default=10000, help="more episodes until one measurement has this many steps")
    a = p.parse_args()
    print(f"cpus={os.cpu_count()} load={os.getloadavg()[0]:.2f} rounds={a.rounds} (best round shown)")
    print(f"{'task':<16} {'episodes':>8} {'steps':>7} {'bare/s':>9} {'eval1/s':>9} {'eval2/s':>9} {'1w/bare':>8} {'2w/bare':>8}")
    for name in a.tasks:
        r = bench(name, a.episodes, a.rounds, a.min_steps)
        print(
            f"{name:<16} {int(r['episodes']):>8} {int(r['steps']):>7} {r['bare']:>9.0f} {r['w1']:>9.0f} {r['w2']:>9.0f} "
            f"{r['w1'] / r['bare']:>8.2f} {r['w2'] / r['bare']:>8.2f}"
        )


if __name__ == "__main__":
    main()
