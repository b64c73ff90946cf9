"""Bring your own robot, from Python: search a policy for PointRobot, then deploy it.

    python examples/own_robot/search_point_robot.py runs/point-py

The task is the env factory itself, with its feedback keys given as options (the task file
point_robot.toml declares the same and more). The search uses random search here so the example
runs in seconds without an LLM; use method="pp" (the default) for PP-ProPS with the embedded
model, or base_url=/model= for your own endpoint. PPPROPS_EXAMPLE_ITERATIONS shortens it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import ppprops

sys.path.insert(0, str(Path(__file__).resolve().parent))
from point_robot import make_point_robot  # noqa: E402  (a top-level factory: worker processes can import it)


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/point-robot")
    result = ppprops.search(
        make_point_robot,
        task_options={"env_kwargs": {"mass": 2.0}, "components": ["reward_distance", "reward_effort"], "diagnostics": ["distance"]},
        method=os.environ.get("PPPROPS_EXAMPLE_METHOD", "random"),
        warmup=10,
        iterations=int(os.environ.get("PPPROPS_EXAMPLE_ITERATIONS", "40")),
        evaluation={"final_episodes": 10, "workers": 2},
        seed=0,
        out=out,
    )
    print(f"best search return {result.best_return:.2f}; final {result.final.mean:.2f} over {len(result.final.returns)} episodes")
    print(f"W has shape {result.W.shape}; run directory {result.run_dir}")

    policy = ppprops.load_policy(out / "best_policy.json")  # what a deployment reads
    env = policy.make_env()
    obs, _ = env.reset(seed=123)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        total += float(reward)
        done = terminated or truncated
    print(f"deployed: return {total:.2f} on a fresh episode")


if __name__ == "__main__":  # worker processes import this file: the search must not run again there
    main()
