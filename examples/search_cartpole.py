"""The whole idea on one page, with the public API only.

    python examples/search_cartpole.py /tmp/pp-demo

1. choose a task and a preset (pp: encoded parameters, scaled rewards, detailed feedback,
   no optimum);
2. start a run: the client draws fresh secrets A and c, samples the warm-up, then asks the
   embedded LLM for 10 candidates it only sees encoded;
3. read the result back from the store and evaluate the deployable policy with no encoding.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ppprops import seeding
from ppprops.config import RunConfig
from ppprops.evaluation import Evaluator
from ppprops.methods import resolve
from ppprops.policy_file import read_policy
from ppprops.report import format_summary, run_summary
from ppprops.runner import start
from ppprops.tasks import get_task

out = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/example")

config = RunConfig(task="CartPole", method="pp", mechanisms=resolve("pp"), warmup=10, iterations=10, final_episodes=10, seed=0)
start(config, out)
print(format_summary(run_summary(out)))

doc, theta = read_policy(out / "best_policy.json")
with Evaluator(get_task(doc["task"])) as ev:
    returns = ev.evaluate(theta, seeding.final_eval_seeds(seed=0, episodes=10)).episode_returns
print(f"deployed policy: {np.mean(returns):.1f} over {len(returns)} episodes")
