"""4. Framework overhead per iteration at D=782 (Humanoid-Torso) with the embedded model.

A real pp search records, per candidate, when it was stored, the seconds its proposer's ``ask``
took and the seconds its episodes took; the client records every LLM round trip. An LLM
iteration's wall time is the time between two stored candidates; the framework's share is what
is left after the LLM round trips and the episodes: prompt building, token counting, parsing,
decoding, encoding, the store, progress. The first LLM iteration also starts the embedded
server, which is shown apart.
"""

from __future__ import annotations

from collections import defaultdict

from _common import Context, Section, config, llm_calls, run_search, table

from ppprops.config import LLMConfig
from ppprops.store import open_store

TASK = "Humanoid-Torso"
TARGET = 2.0  # percent of an iteration's wall time


def run(ctx: Context) -> Section:
    warmup, iters = (1, 1) if ctx.quick else (1, 3)
    run_dir = run_search(config(TASK, warmup=warmup, iterations=iters, top_k=10, seed=2, llm=LLMConfig(context_size=32768, timeout_s=900.0)),
                         ctx.dir("overhead") / "humanoid-torso")
    store = open_store(run_dir)
    try:
        times = store.candidate_times()
    finally:
        store.close()
    llm_s: dict[int, float] = defaultdict(float)
    for c in llm_calls(run_dir):
        llm_s[c["iteration"]] += c["latency_s"]
    rows, per = [], []
    for (_, _, _, prev_created, _, _), (_, source, it, created, ask_s, eval_s) in zip(times, times[1:], strict=False):
        if source == "warmup":
            continue
        wall = created - prev_created
        overhead = wall - llm_s[it] - (eval_s or 0.0)
        ask_extra = (ask_s or 0.0) - llm_s[it]
        per.append({"iteration": it, "wall_s": wall, "llm_s": llm_s[it], "eval_s": eval_s, "overhead_s": overhead,
                    "overhead_in_ask_s": ask_extra, "share_percent": 100 * overhead / wall})
        rows.append([it, f"{wall:.2f}", f"{llm_s[it]:.2f}", f"{eval_s:.3f}", f"{overhead:.3f}", f"{ask_extra:.3f}",
                     f"{100 * overhead / wall:.2f}%"])
    steady = [p for p in per if p["iteration"] > 0]
    share = 100 * sum(p["overhead_s"] for p in per) / sum(p["wall_s"] for p in per)
    steady_share = 100 * sum(p["overhead_s"] for p in steady) / sum(p["wall_s"] for p in steady) if steady else float("nan")
    data = {"iterations": per, "share_percent": share, "steady_share_percent": steady_share, "met": share < TARGET}
    body = [
        f"Humanoid-Torso (D=782), pp, {warmup} warm-up + {iters} LLM iterations, K=10, embedded model (context 32,768):",
        "",
        table(["LLM iteration", "wall (s)", "LLM round trips (s)", "episodes (s)", "framework (s)", "of which in ask (s)",
               "framework share"], rows),
        "",
        f"- Framework share of the LLM iterations' wall time: **{share:.2f}%** over all of them (target under {TARGET:g}%: "
        f"{'met' if data['met'] else 'NOT met'}); {steady_share:.3f}% after the first. Iteration 0 also starts the embedded "
        "server and loads the model, which is most of its framework time.",
    ]
    targets = [("framework share of an iteration, D=782 < 2%", f"{share:.2f}% (after the first: {steady_share:.3f}%)", data["met"])]
    return Section("overhead", "4. Framework overhead", "\n".join(body), data, targets=targets)
