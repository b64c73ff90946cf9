"""What a search's LLM requests used: requests and tokens, in all and by stage, read from the store.

Every answered request stores the server's own counts (``llm_calls.prompt_tokens`` and
``completion_tokens``, from the answer's ``usage``); the reasoning tokens are read from the stored
answer (``usage.completion_tokens_details.reasoning_tokens``, as OpenAI, vLLM and llama.cpp's
server report them). A count the server did not report is unknown: a total over requests of which
any is unknown is None, never 0, and ``unknown`` says how many requests lack it.

The stages: ``search`` (each iteration's request, its transport retries included), ``corrections``
(the requests that ask again after an unusable answer, ``--parse-retries``); the warm-up and the
selection stage send nothing, and are listed with their zeros. With a price (``--price IN,OUT``,
dollars per million prompt and completion tokens) each total has its ``cost_usd``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

STAGES = ("warmup", "search", "corrections", "selection")
COUNTS = ("prompt_tokens", "completion_tokens", "reasoning_tokens")


def reasoning_tokens(response: str | None) -> int | None:
    """The reasoning tokens a stored answer reports (``usage.completion_tokens_details.reasoning_tokens``),
    or None when it reports none (a server without reasoning, or no usage at all)."""
    if not response:
        return None
    try:
        doc = json.loads(response)
    except ValueError:
        return None
    usage = doc.get("usage") if isinstance(doc, dict) else None
    details = usage.get("completion_tokens_details") if isinstance(usage, dict) else None
    value = details.get("reasoning_tokens") if isinstance(details, dict) else None
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def stage_of(call: Mapping[str, Any]) -> str:
    """The stage of one stored LLM call: ``corrections`` for a correction (attempt > 0), else ``search``."""
    return "corrections" if int(call.get("attempt") or 0) > 0 else "search"


def _totals(calls: Sequence[Mapping[str, Any]], price: tuple[float, float] | None = None) -> dict[str, Any]:
    answered = [c for c in calls if c.get("answered", True) and c.get("response")]
    out: dict[str, Any] = {"requests": len(calls)}
    unknown = 0
    for key in COUNTS:
        values = [reasoning_tokens(c.get("response")) if key == "reasoning_tokens" else c.get(key) for c in answered]
        missing = sum(v is None for v in values)
        if key != "reasoning_tokens":
            unknown = max(unknown, missing)
        out[key] = None if missing else int(sum(int(v) for v in values if v is not None))
    out["unknown"] = unknown
    known = price is not None and out["prompt_tokens"] is not None and out["completion_tokens"] is not None
    out["cost_usd"] = (out["prompt_tokens"] * price[0] + out["completion_tokens"] * price[1]) / 1e6 if known and price else None
    return out


def usage(calls: Sequence[Mapping[str, Any]], price: tuple[float, float] | None = None) -> dict[str, Any]:
    """Requests and token totals of a run's stored LLM calls (``RunStore.llm_calls``), in all and
    ``by_stage`` (``STAGES``): each ``{"requests", "prompt_tokens", "completion_tokens",
    "reasoning_tokens", "unknown", "cost_usd"}``, a token total None when any answered request
    lacks it. ``price``: dollars per million prompt and completion tokens (``--price``); the
    cost is None without it or without known totals (reasoning tokens are completion tokens)."""
    whole = _totals(calls, price)
    whole["by_stage"] = {stage: _totals([c for c in calls if stage_of(c) == stage], price) for stage in STAGES}
    return whole


def describe(u: Mapping[str, Any]) -> str:
    """One line for ``ppprops show``: the request count and the token totals, or why they are unknown."""
    if not u["requests"]:
        return "no LLM request"
    if u["prompt_tokens"] is None or u["completion_tokens"] is None:
        return f"{u['requests']} requests; tokens unknown ({u['unknown']} answers reported no usage)"
    reasoning = f" ({u['reasoning_tokens']:,} reasoning)" if u.get("reasoning_tokens") else ""
    cost = f", ${u['cost_usd']:.4f}" if u.get("cost_usd") is not None else ""
    return f"{u['requests']} requests, {u['prompt_tokens']:,} prompt + {u['completion_tokens']:,} completion tokens{reasoning}{cost}"


__all__ = ["COUNTS", "STAGES", "describe", "reasoning_tokens", "stage_of", "usage"]
