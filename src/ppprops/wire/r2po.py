"""R2PO's Critic-LLM prompt: a candidate, its trajectory evidence, and the revision instruction.

The Search-LLM uses the ordinary ProPS prompt (``wire.prompt.build_prompt``). Like everything
in ``wire``, this is built only from values the client chose to show (``Evidence``).
"""

from __future__ import annotations

from dataclasses import dataclass

from .encoded import PromptContext
from .numbers import fmt, fmt_value, fmt_vector
from .prompt import parameters_section, render, task_section


@dataclass(frozen=True)
class Evidence:
    """What the critic sees about one evaluated candidate."""

    params: tuple[float, ...]
    returns: tuple[float, float, float, float]  # mean, std, min, max over the episodes
    episodes: int
    diagnostics: tuple[tuple[str, float | str], ...]  # means over episodes (rates for 0/1 values)
    median_return: float
    median_rollout: tuple[tuple[tuple[float, ...], str], ...]  # (state, action) per step


def _rollout_lines(ev: Evidence, decimals: int) -> str:
    return "\n".join(f"{t}: {fmt_vector(s, decimals)} -> {a}" for t, (s, a) in enumerate(ev.median_rollout))


def build_critic_prompt(ctx: PromptContext, ev: Evidence) -> str:
    """R2PO's Critic-LLM prompt: the task, the proposal's statistics and its median rollout (raw states and actions)."""
    d = ctx.decimals
    mean, std, lo, hi = ev.returns
    diags = "\n".join(f"- {k}: {fmt_value(v, d)}" for k, v in ev.diagnostics) or "- (none)"
    return render(
        "r2po_critic",
        task=task_section(ctx),
        parameters=parameters_section(ctx),
        params=fmt_vector(ev.params, ctx.param_decimals, digits=ctx.param_sig_digits),
        episodes=ev.episodes,
        mean=fmt(mean, d),
        std=fmt(std, d),
        low=fmt(lo, d),
        high=fmt(hi, d),
        diagnostics=diags,
        median_return=fmt(ev.median_return, d),
        steps=len(ev.median_rollout),
        rollout=_rollout_lines(ev, d),
        D=ctx.D,
        last=ctx.D - 1,
    )
