"""What a curious provider may know about a task without any secret (docs/threat-model.md).

The task itself, its public feasible box, the environment's reward structure and time limit,
and the warm-up procedure are public. This module writes down the parts the attacks use.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class PublicFacts:
    """Public facts about a task's returns."""

    task: str
    integer_returns: bool = False  # every per-step reward is an integer (a lattice of returns)
    # raw return = sum(coef * diagnostic) + const, from the environment's definition
    return_formula: dict[str, float] = field(default_factory=dict)
    formula_const: float = 0.0
    # returns a time limit pins: (side, value, diagnostic that marks it, value of that diagnostic)
    caps: tuple[tuple[str, float, str, str], ...] = ()


FACTS: dict[str, PublicFacts] = {
    # +1 per step, 500 steps at most: the return is the episode length; time_limit means 500.
    "CartPole": PublicFacts("CartPole", True, {"episode_length": 1.0}, 0.0, (("max", 500.0, "termination", "time_limit"),)),
    # -1 per step until the goal step (0): return = -episode_length + success; no success means -500.
    "Acrobot": PublicFacts("Acrobot", True, {"episode_length": -1.0, "success": 1.0}, 0.0, (("min", -500.0, "success", "0"),)),
}


def facts_for(task: str) -> PublicFacts:
    return FACTS.get(task, PublicFacts(task))
