"""The whole idea on one page, with the public API only.

    python examples/search_cartpole.py /tmp/pp-demo

1. choose a task and a preset (pp: encoded parameters, scaled rewards, detailed feedback,
   no optimum);
2. search: the client draws fresh secrets A and c, samples the warm-up, then asks the embedded
   LLM for candidates it only sees encoded (PPPROPS_EXAMPLE_ITERATIONS of them, default 10);
3. read the result back and evaluate the deployable policy with no encoding involved.
"""

from __future__ import annotations

import os
import sys

import ppprops

out = sys.argv[1] if len(sys.argv) > 1 else "runs/example"
iterations = int(os.environ.get("PPPROPS_EXAMPLE_ITERATIONS", "10"))

result = ppprops.search("CartPole", method="pp", warmup=10, iterations=iterations, seed=0, out=out, evaluation={"final_episodes": 10})
print(f"{result.task} {result.method}: {len(result.history)} candidates, best search return {result.best_return:.1f}, "
      f"final {result.final.mean:.1f} over {len(result.final.returns)} fresh episodes")

evaluation = ppprops.evaluate_policy(result.policy, episodes=10, seed=0)  # the same fresh episodes
print(f"deployed policy: {evaluation.mean:.1f} over {len(evaluation.returns)} episodes (W is {result.W.shape[0]}x{result.W.shape[1]})")
