"""The seven standard RL algorithms of the paper, as data: where each lives and what actions it takes.

Kept free of imports so the CLI can list the choices without loading torch.
"""

from __future__ import annotations

from dataclasses import dataclass

CONTINUOUS = "continuous"
DISCRETE = "discrete"


@dataclass(frozen=True)
class Algorithm:
    """One algorithm: its Stable-Baselines3 (or sb3-contrib) class and the action spaces it handles."""

    name: str
    module: str
    cls: str
    action_types: frozenset[str]
    title: str

    def applies_to(self, action_type: str) -> bool:
        """True when the algorithm handles ``action_type`` ("discrete" or "continuous")."""
        return action_type in self.action_types


_BOTH = frozenset({CONTINUOUS, DISCRETE})
ALGORITHMS: dict[str, Algorithm] = {
    a.name: a
    for a in (
        Algorithm("ppo", "stable_baselines3", "PPO", _BOTH, "Proximal Policy Optimization"),
        Algorithm("a2c", "stable_baselines3", "A2C", _BOTH, "Advantage Actor-Critic"),
        Algorithm("trpo", "sb3_contrib", "TRPO", _BOTH, "Trust-Region Policy Optimization"),
        Algorithm("sac", "stable_baselines3", "SAC", frozenset({CONTINUOUS}), "Soft Actor-Critic"),
        Algorithm("td3", "stable_baselines3", "TD3", frozenset({CONTINUOUS}), "Twin-Delayed DDPG"),
        Algorithm("ddpg", "stable_baselines3", "DDPG", frozenset({CONTINUOUS}), "Deep Deterministic Policy Gradient"),
        Algorithm("dqn", "stable_baselines3", "DQN", frozenset({DISCRETE}), "Deep Q-Network"),
    )
}
