"""Warm starts: CartPole with pp and the embedded model, from a weak hand-made controller against the random warm-up.

The warm arms give one policy (``init_policies``) in the first warm-up place: half of a balancing
gain (push towards the lean: ``W[2:4, 1] = 0.5``; CartPole's action is an argmax, which ignores the
gain's scale, so this is the full controller), or a weak one that reads the pole angle alone
(``W[2, 1] = 0.5``, no damping); the other arm starts from the random warm-up alone. Each runs 10
warm-up + 20 LLM candidates, the default selection stage and 20 fresh final episodes, on the same seeds (the secrets are fresh in each run)::

    python benchmarks/bench_warm_start.py --seeds 0,1,2 --out /tmp/warm-bench [--arms angle-only]
    python benchmarks/bench_warm_start.py --report --out /tmp/warm-bench

Each run lands in ``OUT/<arm>-s<seed>`` (a finished one is reused); ``--report`` prints the final
evaluation's mean and median over seeds per arm, and the given policy's own search-time return.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

HALF_GAIN = {"W": [[0.0, 0.0], [0.0, 0.0], [0.0, 0.5], [0.0, 0.5]], "b": [0.0, 0.0]}
ANGLE_ONLY = {"W": [[0.0, 0.0], [0.0, 0.0], [0.0, 0.5], [0.0, 0.0]], "b": [0.0, 0.0]}  # no damping: a weak controller
GIVEN = {"half-gain": HALF_GAIN, "angle-only": ANGLE_ONLY}
ARMS = ("random-warmup", "half-gain", "angle-only")


def _run(out: Path, arm: str, seed: int, warmup: int, iterations: int) -> None:
    import ppprops

    run_dir = out / f"{arm}-s{seed}"
    if (run_dir / "best_policy.json").exists():
        return
    if run_dir.exists():
        import shutil

        shutil.rmtree(run_dir)
    t0 = time.perf_counter()
    init = [GIVEN[arm]] if arm in GIVEN else []
    r = ppprops.search("CartPole", method="pp", warmup=warmup, iterations=iterations, seed=seed, out=run_dir, init_policies=init,
                       evaluation={"final_episodes": 20})  # fmt: skip
    assert r.final is not None
    print(f"{run_dir.name}: final {r.final.mean:.1f} in {time.perf_counter() - t0:.0f} s", flush=True)


def _report(out: Path) -> None:
    from ppprops import load_run

    print("| start | seeds | final mean (each seed) | mean | median | the given policy's search return |")
    print("|---|---|---|---|---|---|")
    for arm in ARMS:
        runs = [load_run(p) for p in sorted(out.glob(f"{arm}-s*")) if (p / "best_policy.json").exists()]
        finals = [r.final.mean for r in runs if r.final is not None]
        if not finals:
            continue
        given = [f"{r.history[0].ret:.0f}" for r in runs if r.history and r.history[0].source == "init"]
        print(f"| {arm} | {len(finals)} | {', '.join(f'{f:.1f}' for f in finals)} | {statistics.mean(finals):.1f} | "
              f"{statistics.median(finals):.1f} | {', '.join(given) or '-'} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--out", type=Path, default=Path("/tmp/warm-bench"))
    ap.add_argument("--arms", default=",".join(ARMS))
    ap.add_argument("--report", action="store_true")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    if not a.report:
        for seed in (int(s) for s in a.seeds.split(",")):
            for arm in a.arms.split(","):
                _run(a.out, arm, seed, a.warmup, a.iterations)
    _report(a.out)


if __name__ == "__main__":
    main()
