"""3. Prefix-cache reuse: the static-first layout (default) against one that starts with the history.

The prompts of real searches are rebuilt from their stores in both layouts (the static-first
rebuild is first checked to equal what the search sent, character for character) and replayed
to two fresh embedded servers, one per layout, alternating request by request so that load
changes hit both alike. llama.cpp reports per answer how many prompt tokens it reused from its
cache (``cache_n``) and how many it had to process (``prompt_n``).
"""

from __future__ import annotations

import statistics
from contextlib import ExitStack
from pathlib import Path

from _common import Context, Section, embedded, replay_prompts, sent_prompts, table, timings

from ppprops import seeding
from ppprops.store import open_store

LAYOUTS = ("static-first", "history-first")


def _D(run_dir: Path) -> int:
    store = open_store(run_dir)
    try:
        return len(store.candidates()[0].params)
    finally:
        store.close()


def replay(run_dir: Path) -> dict[str, list[dict[str, float]]]:
    sent = sent_prompts(run_dir)
    rebuilt = replay_prompts(run_dir)
    if [p for _, p in rebuilt] != [p for _, p in sent]:
        raise AssertionError(f"{run_dir}: rebuilt prompts differ from the ones sent; the replay would not be faithful")
    prompts = {lay: replay_prompts(run_dir, layout=lay) for lay in LAYOUTS}
    D = _D(run_dir)
    out: dict[str, list[dict[str, float]]] = {lay: [] for lay in LAYOUTS}
    with ExitStack() as stack:
        clients = {lay: stack.enter_context(embedded()) for lay in LAYOUTS}
        for i in range(len(sent)):
            for lay in LAYOUTS:
                it, text = prompts[lay][i]
                ex = clients[lay].complete([{"role": "user", "content": text}], D=D, seed=seeding.llm_seed(0, it, 0))
                if not ex.ok:
                    raise RuntimeError(f"replay request failed: {ex.error}")
                t = timings(ex.response)
                out[lay].append({"latency_s": ex.latency_s, "cache_n": t.get("cache_n", 0.0), "prompt_n": t.get("prompt_n", 0.0),
                                 "prompt_ms": t.get("prompt_ms", 0.0), "predicted_ms": t.get("predicted_ms", 0.0)})
    return out


def run(ctx: Context) -> Section:
    sources = [("CartPole (D=10)", ctx.cache.get("cache_cartpole_run")), ("Acrobot (D=21)", ctx.cache.get("cache_acrobot_run")),
               ("Ant-Ultra (D=88)", ctx.cache.get("history_K10_run"))]
    rows, data = [], {}
    for label, run_dir in sources:
        if run_dir is None:
            continue
        res = replay(Path(run_dir))
        entry = {}
        for lay in LAYOUTS:
            r = res[lay]
            cached, processed = sum(x["cache_n"] for x in r), sum(x["prompt_n"] for x in r)
            entry[lay] = {"requests": len(r), "cached_share": cached / (cached + processed) if cached + processed else 0.0,
                          "mean_prefill_s": statistics.fmean(x["prompt_ms"] for x in r) / 1000,
                          "mean_latency_s": statistics.fmean(x["latency_s"] for x in r),
                          "mean_decode_s": statistics.fmean(x["predicted_ms"] for x in r) / 1000}
        s, h = entry["static-first"], entry["history-first"]
        entry["latency_ratio_history_first"] = h["mean_latency_s"] / s["mean_latency_s"]
        entry["prefill_ratio_history_first"] = h["mean_prefill_s"] / s["mean_prefill_s"] if s["mean_prefill_s"] else float("nan")
        data[label] = entry
        for lay in LAYOUTS:
            v = entry[lay]
            rows.append([label, lay + (" (default)" if lay == "static-first" else ""), v["requests"], f"{100 * v['cached_share']:.1f}%",
                         f"{v['mean_prefill_s']:.2f}", f"{v['mean_decode_s']:.2f}", f"{v['mean_latency_s']:.2f}"])
    body = ["Prompts of real pp searches replayed in both layouts to two fresh embedded servers, alternating request by request:", "",
            table(["prompts from", "layout", "requests", "prompt tokens reused from the cache", "mean prefill (s)", "mean decoding (s)",
                   "mean response time (s)"], rows), ""]
    for label, e in data.items():
        body.append(f"- {label}: history-first takes {e['latency_ratio_history_first']:.2f}x the response time of static-first "
                    f"({e['prefill_ratio_history_first']:.2f}x the prefill).")
    body.append("- The history is ordered worst to best (the paper's Sort-up), so whenever a new candidate enters the top K, the "
                "worst entry leaves from the front of the history and everything after the fixed sections is new; static-first "
                "saves exactly those fixed sections, history-first saves nothing. When the new candidate does not enter the top K "
                "the prompt repeats and both layouts reuse it whole.")
    targets = [(f"cached share and response time, static-first vs history-first ({label})",
                f"{100 * e['static-first']['cached_share']:.1f}% vs {100 * e['history-first']['cached_share']:.1f}% cached; "
                f"history-first {e['latency_ratio_history_first']:.2f}x the time", None) for label, e in data.items()]
    return Section("cache", "3. Prefix-cache reuse", "\n".join(body), data, targets=targets)
