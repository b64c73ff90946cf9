"""Reading a finished (or interrupted) run back from its store, for `show` and scripts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .config import RunConfig
from .loop import best_candidate
from .store import open_store


def run_summary(run_dir: Path) -> dict[str, Any]:
    """The `ppprops show --json` object. Raw values: this stays on the client."""
    store = open_store(run_dir)
    try:
        config = RunConfig.from_json(store.config())
        cands = store.candidates()
        calls = store.llm_calls()
        fe = store.final_eval()
        best = best_candidate(cands) if cands else None
        failures: dict[str, int] = {}
        for call in calls:
            if call["parse_error"]:
                failures[call["parse_error"]] = failures.get(call["parse_error"], 0) + 1
        return {
            "run_id": store.run_id(),
            "status": store.status(),
            "env": config.task,
            "method": config.method,
            "mechanisms": config.mechanisms.to_json(),
            "seed": config.seed,
            "config": config.to_json(),
            "best": {"return": best.ret, "index": best.index} if best else None,
            "final_eval": {"mean": fe.mean, "std": fe.std, "episodes": len(fe.returns), "returns": list(fe.returns)}
            if fe is not None and fe.returns
            else None,
            "counts": {
                "candidates": len(cands),
                "warmup": sum(c.source == "warmup" for c in cands),
                "llm": sum(c.source == "llm" for c in cands),
                "fallback": sum(c.source == "fallback" for c in cands),
                "clipped_candidates": sum(c.clipped > 0 for c in cands),
                "llm_calls": len(calls),
                "answer_failures": failures,
            },
            "candidates": [
                {
                    "index": c.index,
                    "iteration": c.iteration,
                    "source": c.source,
                    "params": [float(v) for v in c.params],
                    "return": c.ret,
                    "components": c.feedback.components,
                    "diagnostics": c.feedback.diagnostics,
                    "clipped": c.clipped,
                    "note": c.note,
                }
                for c in cands
            ],
            "llm_calls": [
                {
                    "iteration": call["iteration"],
                    "attempt": call["attempt"],
                    "latency_s": call["latency_s"],
                    "prompt_tokens": call["prompt_tokens"],
                    "completion_tokens": call["completion_tokens"],
                    "prompt_chars": call["prompt_chars"],
                    "ok": call["ok"] and call["parse_error"] is None,
                    "error": call["error"] or call["parse_error"],
                }
                for call in calls
            ],
        }
    finally:
        store.close()


def format_summary(s: dict[str, Any]) -> str:
    lines = [
        f"run      {s['run_id']} ({s['status']})",
        f"task     {s['env']}   method {s['method']}   seed {s['seed']}",
    ]
    c = s["counts"]
    lines.append(
        f"evals    {c['candidates']} ({c['warmup']} warm-up, {c['llm']} LLM, {c['fallback']} fallback); "
        f"{c['llm_calls']} LLM calls"
    )
    if c["answer_failures"]:
        lines.append("answers  unusable: " + ", ".join(f"{k} x{v}" for k, v in sorted(c["answer_failures"].items())))
    if s["best"]:
        lines.append(f"best     return {s['best']['return']:.2f} (candidate {s['best']['index']})")
    if s["final_eval"]:
        fe = s["final_eval"]
        lines.append(f"final    {fe['mean']:.2f} +- {fe['std']:.2f} over {fe['episodes']} fresh episodes")
    lat = [x["latency_s"] for x in s["llm_calls"]]
    if lat:
        lines.append(f"llm      mean latency {sum(lat) / len(lat):.2f} s, last prompt {s['llm_calls'][-1]['prompt_chars']} chars")
    return "\n".join(lines)
