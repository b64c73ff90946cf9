"""What a curious provider may know about a task without any secret (docs/threat-model.md).

The task itself, its public feasible box, the environment's reward structure and time limit,
and the warm-up procedure are public. This module writes down the parts the attacks use, and the
public resolution of each reward quantity that the hardened codec dithers (``client.hardening``).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class PublicFacts:
    """Public facts about a task's returns and reward components (Gymnasium's documentation)."""

    task: str
    integer_returns: bool = False  # every per-step reward is an integer (a lattice of returns)
    # raw return = sum(coef * diagnostic) + const, from the environment's definition
    return_formula: dict[str, float] = field(default_factory=dict)
    formula_const: float = 0.0
    # returns a time limit pins: (side, value, diagnostic that marks it, value of that diagnostic)
    caps: tuple[tuple[str, float, str, str], ...] = ()
    # public range of one episode's return (for the warped-lattice search), None if unbounded
    return_range: tuple[float, float] | None = None
    # public step of each reward quantity in one episode ("return" or a component name): values
    # are whole multiples of it. The hardened codec dithers these by a secret amount below one step.
    resolution: dict[str, float] = field(default_factory=dict)
    # locomotion: the survive component is healthy_reward per step; a saturated controller costs
    # exactly ctrl_per_step per step (ctrl_cost_weight * n_a * bound^2); episodes end at time_limit
    survive: str | None = None
    healthy_reward: float | None = None
    ctrl: str | None = None
    ctrl_per_step: float | None = None
    time_limit: int | None = None
    components: tuple[str, ...] = ()  # every reward component of the task (the ones that add up to the return)
    components_sum_to_return: bool = False


FACTS: dict[str, PublicFacts] = {
    # +1 per step, 500 steps at most: the return is the episode length; time_limit means 500.
    "CartPole": PublicFacts("CartPole", True, {"episode_length": 1.0}, 0.0, (("max", 500.0, "termination", "time_limit"),),
                            return_range=(1.0, 500.0), resolution={"return": 1.0}, time_limit=500),
    # -1 per step until the goal step (0): return = -episode_length + success; no success means -500.
    "Acrobot": PublicFacts("Acrobot", True, {"episode_length": -1.0, "success": 1.0}, 0.0, (("min", -500.0, "success", "0"),),
                           return_range=(-500.0, -1.0), resolution={"return": 1.0}, time_limit=500),
}

# Ant-v5: healthy_reward 1, ctrl_cost_weight 0.5, 8 actuators in [-1, 1]; Humanoid-v5: healthy_reward
# 5, ctrl_cost_weight 0.1, 17 actuators in [-0.4, 0.4]; both end at 1000 steps. The four components
# (reward_forward, reward_survive, reward_ctrl, reward_contact) add up to the return.
_LOCO = ("reward_forward", "reward_survive", "reward_ctrl", "reward_contact")
LOCOMOTION: dict[str, PublicFacts] = {
    "Ant": PublicFacts("Ant", resolution={"reward_survive": 1.0}, survive="reward_survive", healthy_reward=1.0,
                       ctrl="reward_ctrl", ctrl_per_step=0.5 * 8 * 1.0**2, time_limit=1000, components=_LOCO, components_sum_to_return=True),
    "Humanoid": PublicFacts("Humanoid", resolution={"reward_survive": 5.0}, survive="reward_survive", healthy_reward=5.0,
                            ctrl="reward_ctrl", ctrl_per_step=0.1 * 17 * 0.4**2, time_limit=1000, components=_LOCO,
                            components_sum_to_return=True),
}


def facts_for(task: str) -> PublicFacts:
    """Facts by task name (``Ant-Ultra`` and the other observation configurations share their robot's)."""
    if task in FACTS:
        return FACTS[task]
    family = task.split("-")[0]
    if family in LOCOMOTION:
        return LOCOMOTION[family]
    return PublicFacts(task)
