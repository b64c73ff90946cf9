"""Builds the public prompt context from a task and the run's mechanisms.

This is where a raw fact (the optimal return) is either withheld or passed through the codec;
the wire side only ever receives the result.
"""

from __future__ import annotations

from ..config import RunConfig
from ..tasks.base import Task
from ..wire.encoded import PromptContext
from .codec import Codec


def prompt_context(task: Task, config: RunConfig, codec: Codec) -> PromptContext:
    m = config.mechanisms
    text = task.text
    reward_text = text.reward_structure if m.disclose_reward_structure else text.reward_hint
    optimum = None
    if m.disclose_optimum and task.optimal_return is not None:
        optimum = codec.scale(task.optimal_return)
    return PromptContext(
        summary=text.summary,
        observations=tuple(zip(task.observation.names, text.observations, strict=True)),
        actions=text.actions,
        discrete=task.discrete,
        reward_text=reward_text,
        hints=text.hints,
        encoded_params=m.encode_params,
        scaled_rewards=m.scale_rewards,
        detailed_feedback=m.detailed_feedback,
        param_range=None if m.encode_params else config.box,
        optimum=optimum,
        component_notes=tuple((k, text.components.get(k, k)) for k in task.components),
        diagnostic_notes=tuple((k, text.diagnostics.get(k, k)) for k in task.diagnostics),
        decimals=config.decimals,
        history_limit=config.top_k,
    )
