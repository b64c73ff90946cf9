"""R2PO (reflective prompted policy optimization) as a two-stage proposer.

Each two-stage iteration asks twice: a Search-LLM proposes a candidate from the history (the
ordinary ProPS prompt); after it is evaluated, a Critic-LLM revises it from trajectory evidence
(return and episode-length statistics, success and failure rates, the median rollout as a
state -> action sequence) and is told to keep what works. Both are evaluated and recorded; only
the better of the two enters the history the Search-LLM sees. So ``--iterations 50`` means 25
two-stage iterations and 50 LLM calls, as in the paper.

Before each call the prompt's size is checked against the model's context window; a prompt
that would not fit stops the run (``StopSearch``), which then reports the best policy found.
The size is estimated locally, never by sending the prompt anywhere: from the tokens-per-character
ratio of the server's own usage counts of earlier answers (with a 5% margin), and before the first
answer by ``estimate_tokens`` (a conservative estimate: one token per two characters).

Privacy: the critic is shown raw states and actions, so R2PO runs without any privacy mechanism
(``methods.check_method`` refuses them; docs/threat-model.md says why encoding them would not hold).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..llm.protocol import Exchange
from ..values import Candidate
from ..wire.forms import CHAT, CRITIC
from ..wire.r2po import Evidence, build_critic_prompt
from .base import Proposal, SearchProposer, StopSearch
from .llm import LLMProposer, LLMSearch

if TYPE_CHECKING:
    pass

Rollout = Callable[[np.ndarray, int], tuple[float, list[tuple[tuple[float, ...], str]]]]

SEARCH, CRITIC_SOURCE = "r2po-search", "r2po-critic"
TEMPLATE_MARGIN = 32  # tokens a chat template adds around the messages


def estimate_tokens(text: str) -> int:
    """A prompt's tokens before any answer says better: one per two characters (digit-heavy prompts
    tokenize densely; no tokenizer of the endpoint's model is known here), plus the chat template's."""
    return len(text) // 2 + TEMPLATE_MARGIN


class _Critic(LLMProposer):
    """The LLM proposer machinery (retries, parsing, decoding, fallback) with the critic's prompt form."""

    evidence: Evidence | None = None

    def prompt(self) -> str:
        assert self.evidence is not None
        return build_critic_prompt(self.ctx, self.evidence)


class R2POProposer(SearchProposer):
    """R2PO's two stages as one proposer: even asks are the Search-LLM's proposal, odd asks the
    Critic-LLM's revision of it (see the module docstring). Raises StopSearch when a prompt would
    not fit ``context_window`` tokens with its answer.
    """

    def __init__(self, run: LLMSearch, *, rollout: Rollout, context_window: int, max_tokens: int,
                 count_tokens: Callable[[str], int] = estimate_tokens) -> None:
        """``run`` is what both stages share (``proposers.llm.LLMSearch``); ``rollout(theta, seed)``
        re-runs one episode for the critic's evidence; ``context_window`` and ``max_tokens`` bound a
        request; ``count_tokens`` estimates a prompt before the first answer's usage counts."""
        self._ratio: float | None = None  # prompt tokens per character, from the usage counts so far
        self.search = LLMProposer(run, form=CHAT, on_answer=self._observe)
        self.critic = _Critic(run, form=CRITIC, on_answer=self._observe)
        self.rollout = rollout
        self.count_tokens = count_tokens
        self.context_window = context_window
        self.max_tokens = max_tokens
        self.pending: Candidate | None = None

    def latency(self) -> float | None:
        """Seconds of the latest LLM call of either stage (None before the first)."""
        return self.critic.latency() or self.search.latency()

    def _observe(self, ex: Exchange) -> None:
        if ex.prompt_tokens and ex.prompt_chars:
            self._ratio = max(self._ratio or 0.0, ex.prompt_tokens / ex.prompt_chars)

    def prompt_tokens(self, prompt: str) -> int:
        """Tokens the prompt will take: measured ratio x characters (+5%), else the conservative estimate."""
        if self._ratio is not None:
            return math.ceil(len(prompt) * self._ratio * 1.05) + TEMPLATE_MARGIN
        return self.count_tokens(prompt)

    def _check_fits(self, prompt: str, iteration: int) -> None:
        need = self.prompt_tokens(prompt) + self.max_tokens
        if need > self.context_window:
            raise StopSearch(
                f"context overflow at LLM call {iteration}: the prompt needs about {need} tokens"
                f" (with the answer), the context window holds {self.context_window}"
            )

    def evidence(self, c: Candidate) -> Evidence:
        """The critic's evidence on candidate ``c``: return statistics over its episodes (encoded) and
        the rollout of its median episode (raw states and actions, re-run from that episode's seed).
        """
        fb = c.feedback_enc
        rets = np.asarray(fb.episode_returns, dtype=float)
        order = np.argsort(rets, kind="stable")
        median_idx = int(order[(len(order) - 1) // 2])
        _, steps = self.rollout(c.params, c.seeds[median_idx])
        return Evidence(
            params=tuple(float(v) for v in c.params_enc),
            returns=(float(rets.mean()), float(rets.std()), float(rets.min()), float(rets.max())),
            episodes=len(rets),
            diagnostics=tuple(fb.diagnostics.items()),
            median_return=float(rets[median_idx]),
            median_rollout=tuple(steps),
        )

    def ask(self, iteration: int) -> Proposal:
        """Even ``iteration``: the Search-LLM's proposal; odd: the Critic-LLM's revision of the last one.

        Raises StopSearch on a context overflow, RuntimeError for a critic stage with nothing to revise.
        """
        if iteration % 2 == 0:
            self._check_fits(self.search.prompt(), iteration)
            p = self.search.ask(iteration)
            return Proposal(p.theta, SEARCH if p.source == "llm" else p.source, p.clipped, p.note)
        if self.pending is None:
            raise RuntimeError("R2PO critic stage without an evaluated search candidate")
        self.critic.evidence = self.evidence(self.pending)
        self.critic.best = self.pending  # a failed revision falls back to a perturbation of the proposal
        self._check_fits(self.critic.prompt(), iteration)
        p = self.critic.ask(iteration)
        return Proposal(p.theta, CRITIC_SOURCE if p.source == "llm" else p.source, p.clipped, p.note)

    def tell(self, candidate: Candidate) -> None:
        """Warm-up goes to the search history; of each proposal/revision pair only the better enters it."""
        if candidate.source in ("warmup", "init"):  # the warm-up, its given policies too
            self.search.tell(candidate)
        elif self.pending is None:  # the search stage's candidate (or its fallback)
            self.pending = candidate
        else:  # the critic stage's: keep the better of proposal and revision
            better = candidate if candidate.ret > self.pending.ret else self.pending
            self.search.tell(better)
            self.pending = None
