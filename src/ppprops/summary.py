"""Reading a finished (or interrupted) run back from its store, for `show` and scripts."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

from .baselines.record import format_rl_summary, rl_summary
from .errors import PPPropsError
from .loop import best_candidate, pooled_returns, search_candidates, select_best
from .rundir import StoredRun, open_run
from .status import RunKind, RunStatus, effective
from .usage import describe, usage


def _finite(x: Any) -> Any:
    """JSON has no NaN or Infinity: non-finite numbers (numerical faults) come out as null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _fault_counts(cands: list[Any], calls: list[dict[str, Any]]) -> dict[str, Any]:
    """Endpoint faults, retries, unusable answers and numerical faults, each counted per kind."""
    transport = Counter(c["error_kind"] or "unknown" for c in calls if not c["ok"] and c.get("answered", True))
    answers = Counter(c["parse_error"] for c in calls if c["ok"] and c["parse_error"])
    reasons: Counter[str] = Counter()
    for c in cands:
        if c.source == "fallback":
            reasons[c.note.removeprefix("after ").split(" (")[0] or "unknown"] += 1
    numerical = sum(
        (not math.isfinite(c.ret)) or bool(c.feedback.diagnostics.get("numerical_fault")) for c in cands
    )
    return {
        "llm_requests_failed": sum(transport.values()),
        "llm_unanswered": sum(1 for c in calls if not c.get("answered", True)),  # sent, no answer recorded (written ahead)
        "transport_failures": dict(sorted(transport.items())),
        "retries": sum(1 for c in calls if c["retry"]),
        "answer_failures": dict(sorted(answers.items())),
        "answers_from_reasoning": sum(1 for c in calls if c["answer_source"] == "reasoning"),
        "llm_unavailable": reasons.get("llm_unavailable", 0),
        "fallback_reasons": dict(sorted(reasons.items())),
        "numerical_faults": numerical,
    }


def _policy_key(config: Any) -> dict[str, str]:
    """``{"policy": "mlp:16 (tanh), D = 81"}`` for a run of an MLP; nothing for the paper's linear policy (as before)."""
    spec = (config.task_spec or {}).get("policy")
    if not spec:
        return {}
    from .policy import parse_policy

    policy = parse_policy(spec)
    task = config.make_task()
    return {"policy": f"{policy.label()}, D = {task.D}"}


def run_summary(run_dir: Path) -> dict[str, Any]:
    """The `ppprops show --json` object. Raw values: this stays on the client.

    Keys: run_id, status, stop_reason (why a stopped run stopped, else None), stop_rule (the stop
    rule that ended the search early: rule, why, end, the trial number where the selection stage
    began; else None), usage (``ppprops.usage``: requests and tokens, by stage),
    env, number_format (resolved), method, mechanisms, seed, config, endpoint_changes (LLM endpoints
    changed on resume), best, final_eval, counts, candidates, llm_calls (RL runs: ``training``
    too). Raises StoreError for a directory that holds no readable run."""
    with open_run(run_dir) as run:
        return summarize(run)


def summarize(run: StoredRun) -> dict[str, Any]:
    """``run_summary``'s object for a run already open (``rundir.open_run``)."""
    store = run.store
    if run.kind is RunKind.RL:  # same keys, no candidates, plus "training"
        return rl_summary(store)
    config = run.config
    cands = store.candidates()
    calls = store.llm_calls()
    adaptations = store.llm_adaptations()
    fe = store.final_eval()
    out = store.pending_trials()
    pending = out[0] if out else None
    failed = store.failed_trials()
    search = search_candidates(cands)
    best = select_best(cands) if search else None
    first_pick = best_candidate(search) if search else None  # the best search-time return (Algorithm 1's theta_best)
    pooled = pooled_returns(cands).get(best.index) if best is not None else None
    status, reason = effective(store.status(), run.path)
    early = store.stop_state()  # a stop rule that ended the search early (ppprops.stopping)
    notes = []
    from .wire.forms import FORMS

    quiet = [str(c["form"]) for c in calls if c.get("form") in FORMS and not FORMS[str(c["form"])].shows_feedback]
    if config.mechanisms.detailed_feedback and quiet:
        try:
            declared = run.task.detailed_feedback()
        except PPPropsError:
            declared = ""
        if declared:
            notes.append(f"the {quiet[0]} form showed the LLM the returns only, not the detailed feedback of this task ({declared}); "
                         "--prompt-form chat shows it")
    return _finite({
        "run_id": store.run_id(),
        "status": status.stored(reason) if status is not RunStatus.INTERRUPTED or not reason else f"interrupted ({reason})",
        "stop_reason": reason if status is RunStatus.STOPPED and reason else early.get("reason") if early.get("end") is not None else None,
        "stop_rule": {k: early[k] for k in ("rule", "why", "end")} if early.get("end") is not None else None,
        "pending_trial": None if pending is None else pending.number,
        "trials_out": [{"trial": t.number, "worker": t.worker, "source": t.source} for t in out],
        "failed_trials": [{"trial": t.number, "source": t.source, "worker": t.worker, "reason": why} for t, why in failed],
        "notes": notes,
        "env": config.task,
        **_policy_key(config),
        "number_format": config.numbers,  # resolved: what the prompts wrote (auto names no format)
        "method": config.method,
        "mechanisms": config.mechanisms.to_json(),
        "seed": config.seed,
        "config": config.to_json(),
        "endpoint_changes": store.endpoint_changes(),
        "best": {"return": best.ret, "index": best.index,
                 "selection": {"mean": float(sum(pooled) / len(pooled)), "episodes": len(pooled)} if pooled else None,
                 "search_best": {"return": first_pick.ret, "index": first_pick.index} if first_pick is not None else None}
        if best else None,
        "final_eval": {"mean": fe.mean, "std": fe.std, "episodes": len(fe.returns), "returns": list(fe.returns)}
        if fe is not None and fe.returns
        else None,
        "counts": {
            "candidates": len(cands),
            "failed": len(failed),
            "warmup": sum(c.source == "warmup" for c in cands),
            "llm": sum(c.source == "llm" for c in cands),
            "fallback": sum(c.source == "fallback" for c in cands),
            "by_source": dict(Counter(c.source for c in cands)),
            "clipped_candidates": sum(c.clipped > 0 for c in cands),
            "episodes": {"search": sum(len(c.seeds) or 1 for c in search),
                         "selection": sum(len(c.seeds) or 1 for c in cands if c.reevaluates is not None),
                         "final": len(fe.returns) if fe is not None else 0},
            "llm_calls": len(calls),
            "request_adaptations": len(adaptations),
            **_fault_counts(cands, calls),
        },
        "llm_adaptations": [{"iteration": a["iteration"], "change": a["change"]} for a in adaptations],
        "candidates": [
            {
                "index": c.index,
                "iteration": c.iteration,
                "source": c.source,
                "params": [float(v) for v in c.params],
                "return": c.ret,
                "seeds": [int(x) for x in c.seeds],  # one per episode, in order: reset an env with them to replay the trial
                "episode_returns": [float(r) for r in c.feedback.episode_returns],
                "components": c.feedback.components,
                "diagnostics": c.feedback.diagnostics,
                "clipped": c.clipped,
                "note": c.note,
                "reevaluates": c.reevaluates,
            }
            for c in cands
        ],
        "usage": usage(calls, config.llm.price),
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
                "error_kind": call["error_kind"] or call["parse_error"],
                "retry": call["retry"],
                "answer_source": call["answer_source"],
                "answered": call["answered"],
            }
            for call in calls
        ],
    })


def _endpoint(e: dict[str, Any]) -> str:
    if not e.get("base_url"):
        return "the embedded model"
    key = f", key from ${e['api_key_env']}" if e.get("api_key_env") else ""
    return f"{e['base_url']} ({e.get('model')}{key})"


def format_summary(s: dict[str, Any]) -> str:
    """The text ``ppprops show`` (and the end of ``ppprops run``) prints for ``run_summary``'s object.

    A search whose candidates were mostly fallbacks (more than half; all of them: "the LLM
    contributed nothing") gets a ``WARNING`` line right under the counts, with the reasons."""
    if s.get("training") is not None:
        return format_rl_summary(s)
    lines = [
        f"run      {s['run_id']} ({s['status']})",
        f"task     {s['env']}   method {s['method']}   seed {s['seed']}" + (f"   policy {s['policy']}" if "policy" in s else "")
        + ("   numbers grid" if s.get("number_format") == "grid" else ""),  # decimal, the paper's, is not named
    ]
    c = s["counts"]
    sources = ", ".join(f"{n} {name}" for name, n in c["by_source"].items())
    lines.append(f"evals    {c['candidates']}" + (f" ({sources})" if sources else "") + f"; {c['llm_calls']} LLM calls")
    rule = s.get("stop_rule")
    if rule:
        lines.append(f"stopped  {s['stop_reason'] or 'the search ended early'}: {rule['why']}")
    searched = c["candidates"] - c.get("warmup", 0) - sum(c.get("by_source", {}).get(k, 0) for k in ("reeval", "init"))
    fallbacks = c.get("fallback", 0)
    if searched and fallbacks * 2 > searched:  # the LLM contributed nothing, or little: say so first
        why = ", ".join(f"{k} x{v}" for k, v in c.get("fallback_reasons", {}).items()) or "no reason recorded"
        head = (f"every one of the {searched} search candidates was a fallback: the LLM contributed nothing"
                if fallbacks == searched else
                f"{fallbacks} of the {searched} search candidates were fallbacks: the LLM contributed little")
        lines.append(f"WARNING  {head} ({why}; the best policy plus noise was evaluated instead)")
    for note in s.get("notes") or []:
        lines.append(f"note     {note}")
    out = s.get("trials_out") or []
    if out:
        lines.append(f"out      {len(out)} trial(s): " + ", ".join(
            f"{t['trial']} ({'held by nobody yet' if t['worker'] is None else 'held by ' + (t['worker'] or 'the unnamed worker')})"
            for t in out))
    failed = s.get("failed_trials") or []
    if failed:
        lines.append(f"failed   {len(failed)} trial(s), never shown to the LLM nor selected: " + "; ".join(
            f"{t['trial']} ({t['reason']})" for t in failed))
    ep = c.get("episodes")
    if ep:
        lines.append(f"episodes {ep['search']} in the search, {ep['selection']} re-evaluating the best candidates, {ep['final']} in the "
                     "final evaluation")
    if c["answer_failures"]:
        lines.append("answers  unusable: " + ", ".join(f"{k} x{v}" for k, v in sorted(c["answer_failures"].items())))
    if c.get("answers_from_reasoning"):
        lines.append(f"answers  {c['answers_from_reasoning']} taken from the reasoning text (empty content)")
    if c.get("llm_unanswered"):
        lines.append(f"llm      {c['llm_unanswered']} request(s) sent and never answered (in flight, or the process ended while "
                     "they were); recorded before they were sent, the audit reads them like the others")
    if c.get("transport_failures"):
        lines.append(
            "endpoint failed tries: " + ", ".join(f"{k} x{v}" for k, v in c["transport_failures"].items())
            + f"; {c['retries']} retries, {c['llm_unavailable']} iterations skipped as unavailable"
        )
    for a in s.get("llm_adaptations", []):
        lines.append(f"endpoint adapted at LLM iteration {a['iteration']}: {a['change']}")
    if c.get("answer_failures", {}).get("length"):
        lines.append("answers  cut off at the token limit: raise --max-tokens (or lower --reasoning-effort)")
    if c.get("answer_failures", {}).get("context_full"):
        lines.append("answers  cut off because the server's context was full (not --max-tokens): start the server with a "
                     "larger context (llama.cpp -c/--ctx-size, Ollama num_ctx; the embedded model: --context-size) or "
                     "send a smaller prompt (--top-k, --param-digits)")
    if c.get("fallback_reasons"):
        lines.append("fallback " + ", ".join(f"{k} x{v}" for k, v in c["fallback_reasons"].items()))
    if c.get("numerical_faults"):
        lines.append(f"numeric  {c['numerical_faults']} candidates hit NaN/Inf (episode ended, kept out of the prompt)")
    for ch in s.get("endpoint_changes") or []:
        lines.append(f"endpoint changed on resume after {ch['candidates']} candidates: {_endpoint(ch['from'])} -> {_endpoint(ch['to'])}")
    if s["best"] and s["best"]["return"] is not None:
        b = s["best"]
        sel = b.get("selection")
        if sel:
            first = b.get("search_best") or {}
            lines.append(f"best     candidate {b['index']}: mean {sel['mean']:.2f} over {sel['episodes']} episodes (search and "
                         f"re-evaluation); the best single search return was {first.get('return', float('nan')):.2f} "
                         f"(candidate {first.get('index')})")
        else:
            lines.append(f"best     return {b['return']:.2f} (candidate {b['index']})")
    if s["final_eval"]:
        fe = s["final_eval"]
        lines.append(f"final    {fe['mean']:.2f} +- {fe['std']:.2f} over {fe['episodes']} fresh episodes")
    lat = [x["latency_s"] for x in s["llm_calls"] if x.get("answered", True)]
    if lat:
        spent = f"; {describe(s['usage'])}" if s.get("usage") else ""
        lines.append(f"llm      mean latency {sum(lat) / len(lat):.2f} s, last prompt {s['llm_calls'][-1]['prompt_chars']} chars{spent}")
    return "\n".join(lines)
