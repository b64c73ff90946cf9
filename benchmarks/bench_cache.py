"""3. Prefix-cache reuse: the document form (the embedded default), and the chat form's two layouts.

The prompts of real searches are rebuilt from their stores in each arm (the rebuild in the form
the search used is first checked to equal what it sent, character for character) and replayed to
fresh embedded servers, one per arm, alternating request by request so that load changes hit
them alike. llama.cpp reports per answer how many prompt tokens it reused from its cache
(``cache_n``) and how many it had to process (``prompt_n``). The chat arms compare the
static-first layout (default for chat endpoints) with one that starts with the history.
"""

from __future__ import annotations

import statistics
from contextlib import ExitStack
from pathlib import Path

from _common import Context, Section, embedded, replay_requests, request_for, run_form, sent_prompts, table, timings

from ppprops import seeding
from ppprops.store import open_store

# (arm, prompt form, chat layout)
ARMS = (("document", "document", "static-first"), ("static-first", "chat", "static-first"),
        ("history-first", "chat", "history-first"))


def _D(run_dir: Path) -> int:
    store = open_store(run_dir)
    try:
        return len(store.candidates()[0].params)
    finally:
        store.close()


def replay(run_dir: Path) -> dict[str, list[dict[str, float]]]:
    sent = sent_prompts(run_dir)
    own = run_form(run_dir)
    rebuilt = replay_requests(run_dir, form=own)
    if [p for _, p, _ in rebuilt] != [p for _, p in sent]:
        raise AssertionError(f"{run_dir}: rebuilt prompts differ from the ones sent; the replay would not be faithful")
    requests = {arm: replay_requests(run_dir, form=form, layout=layout) for arm, form, layout in ARMS}
    D = _D(run_dir)
    out: dict[str, list[dict[str, float]]] = {arm: [] for arm, _, _ in ARMS}
    with ExitStack() as stack:
        clients = {arm: stack.enter_context(embedded()) for arm, _, _ in ARMS}
        for i in range(len(sent)):
            for arm, form, _ in ARMS:
                it, text, grammar = requests[arm][i]
                seed = seeding.llm_seed(0, it, 0)
                ex = clients[arm].send(request_for(form, text, D, it, grammar), seed=seed)
                if not ex.ok:
                    raise RuntimeError(f"replay request failed: {ex.error}")
                t = timings(ex.response)
                out[arm].append({"latency_s": ex.latency_s, "cache_n": t.get("cache_n", 0.0), "prompt_n": t.get("prompt_n", 0.0),
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
        entry = {"recorded_form": run_form(Path(run_dir))}
        for arm, _, _ in ARMS:
            r = res[arm]
            cached, processed = sum(x["cache_n"] for x in r), sum(x["prompt_n"] for x in r)
            entry[arm] = {"requests": len(r), "cached_share": cached / (cached + processed) if cached + processed else 0.0,
                          "mean_prefill_s": statistics.fmean(x["prompt_ms"] for x in r) / 1000,
                          "mean_latency_s": statistics.fmean(x["latency_s"] for x in r),
                          "mean_decode_s": statistics.fmean(x["predicted_ms"] for x in r) / 1000,
                          "mean_prompt_tokens": statistics.fmean(x["cache_n"] + x["prompt_n"] for x in r)}
        s, h, d = entry["static-first"], entry["history-first"], entry["document"]
        entry["latency_ratio_history_first"] = h["mean_latency_s"] / s["mean_latency_s"]
        entry["prefill_ratio_history_first"] = h["mean_prefill_s"] / s["mean_prefill_s"] if s["mean_prefill_s"] else float("nan")
        entry["latency_ratio_document"] = d["mean_latency_s"] / s["mean_latency_s"]
        data[label] = entry
        for arm, form, layout in ARMS:
            v = entry[arm]
            name = "document (embedded default)" if form == "document" else f"chat, {layout}" + (" (default)" if layout == "static-first" else "")
            rows.append([f"{label}, {entry['recorded_form']} run", name, v["requests"], f"{v['mean_prompt_tokens']:.0f}",
                         f"{100 * v['cached_share']:.1f}%", f"{v['mean_prefill_s']:.2f}", f"{v['mean_decode_s']:.2f}",
                         f"{v['mean_latency_s']:.2f}"])
    body = ["Prompts of real pp searches replayed in each arm to fresh embedded servers, alternating request by request:", "",
            table(["prompts from", "arm", "requests", "mean prompt tokens", "prompt tokens reused from the cache",
                   "mean prefill (s)", "mean decoding (s)", "mean response time (s)"], rows), ""]
    for label, e in data.items():
        body.append(f"- {label}: the document form takes {e['latency_ratio_document']:.2f}x the response time of the chat form "
                    f"(static-first); history-first takes {e['latency_ratio_history_first']:.2f}x ({e['prefill_ratio_history_first']:.2f}x "
                    "the prefill).")
    body.append("- The history is ordered worst to best (the paper's Sort-up), so whenever a new candidate enters the top K, the "
                "worst entry leaves from the front of the history and everything after the fixed part is new; the chat form's "
                "static-first layout saves its fixed sections, history-first saves nothing, and the document form has only a "
                "one-line header to save but far fewer tokens in all. When the new candidate does not enter the top K the prompt "
                "repeats and every arm reuses it whole.")
    targets = [(f"cached share and response time: document vs chat static-first vs chat history-first ({label})",
                f"{100 * e['document']['cached_share']:.1f}% vs {100 * e['static-first']['cached_share']:.1f}% vs "
                f"{100 * e['history-first']['cached_share']:.1f}% cached; {e['latency_ratio_document']:.2f}x vs 1 vs "
                f"{e['latency_ratio_history_first']:.2f}x the time", None) for label, e in data.items()]
    return Section("cache", "3. Prefix-cache reuse", "\n".join(body), data, targets=targets)
