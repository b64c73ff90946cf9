"""Builds the public prompt context from a task and the run's mechanisms.

This is where a raw fact (the optimal return) is either withheld or passed through the codec;
the wire side only ever receives the result. Hardened runs also drop the notes of hidden
diagnostics and describe their encodings without claiming what they do not keep (signs, zero).
"""

from __future__ import annotations

from ..config import RunConfig
from ..tasks.base import Task
from ..wire.encoded import PromptContext
from .codec import Codec


def encoding_words(codec: Codec) -> tuple[str, str]:
    """How the prompt describes the parameter and reward encodings: scale, affine or warp."""
    params = "warp" if codec.warp_params else "affine" if codec.offsets else "scale"
    rewards = "warp" if codec.warp_rewards else "affine" if codec.offsets else "scale"
    return params, rewards


def warmup_box(config: RunConfig) -> tuple[float, float]:
    """The public encoded box an encoded warm-up draws from: the public box's width, centred on 0."""
    half = (config.box[1] - config.box[0]) / 2.0
    return (-half, half)


def prompt_context(task: Task, config: RunConfig, codec: Codec) -> PromptContext:
    """The public context of every prompt (wire side): task text as the mechanisms allow, D, the box
    (encoded when the warm-up is drawn in the encoded space), digits, and the switches. Holds no secret.
    """
    m = config.mechanisms
    text = task.text
    reward_text = text.reward_structure if m.disclose_reward_structure else text.reward_hint
    optimum = None
    if m.disclose_optimum and task.optimal_return is not None:
        optimum = codec.scale(task.optimal_return)
    param_words, reward_words = encoding_words(codec)
    diagnostics = [k for k in task.diagnostics if k not in codec.hidden_diagnostics]
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
        component_notes=tuple((k, text.components.get(k, k)) for k in task.components if k not in codec.hidden_components),
        diagnostic_notes=tuple((k, text.diagnostics.get(k, k)) for k in diagnostics),
        decimals=config.decimals,
        params_style=config.prompt_params,
        param_digits=config.digits(),
        layout=config.prompt_layout,
        title=task.name,
        history_limit=config.top_k,
        param_encoding=param_words,
        reward_encoding=reward_words,
        warmup_range=warmup_box(config) if (m.encoded_warmup and m.encode_params) else None,
        describe_task=m.describe_task,
    )
