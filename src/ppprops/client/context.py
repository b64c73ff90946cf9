"""Builds the public prompt context from a task and the run's mechanisms.

This is where a raw fact (the optimal return) is either withheld or passed through the codec;
the wire side only ever receives the result. Hardened runs also drop the notes of hidden
diagnostics and describe their encodings without claiming what they do not keep (signs, zero).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..tasks.base import Task
from ..wire.encoded import PromptContext
from .codec import Codec
from .mechanisms import Mechanisms


@dataclass(frozen=True)
class PromptSettings:
    """The run settings a prompt depends on (``RunConfig.prompt`` makes them): the mechanisms, the
    public box, and how numbers and sections are written. Public; holds no secret.

    ``form`` is the resolved prompt form (``chat`` or ``document``); ``param_digits`` the
    significant digits of a parameter in it (0: fixed decimals); ``top_k`` the history limit K
    (0: unbounded), which only shapes the wording; ``explore`` the document form's rule of sampling
    hotter when the search is stuck.
    """

    mechanisms: Mechanisms
    box: tuple[float, float]
    decimals: int = 2
    params_style: str = "list"
    param_digits: int = 3
    layout: str = "static-first"
    top_k: int = 10
    form: str = "chat"
    explore: bool = True  # the document form's exploration when stuck (wire.document.STALL_AFTER)
    number_format: str = "decimal"  # how encoded parameters are written (wire.numbers.NUMBER_FORMATS)


def encoding_words(codec: Codec) -> tuple[str, str]:
    """How the prompt describes the parameter and reward encodings: scale, affine or warp."""
    params = "warp" if codec.warp_params else "affine" if codec.offsets else "scale"
    rewards = "warp" if codec.warp_rewards else "affine" if codec.offsets else "scale"
    return params, rewards


def warmup_box(box: tuple[float, float], scale: float = 1.0) -> tuple[float, float]:
    """The public encoded box an encoded warm-up draws from: the public ``box``'s width, centred on 0,
    times ``scale`` (``Codec.warmup_scale``: the public grid scale G on the grid, else 1, times the
    prior's largest a_j, 3, for warped parameters)."""
    half = scale * (box[1] - box[0]) / 2.0
    return (-half, half)


NEUTRAL_TITLE = "Task"  # what a prompt calls a task whose file names nothing for the provider


def prompt_title(task: Task, mechanisms: Mechanisms) -> str:
    """The task's name as a prompt shows it: the task file's ``prompt_name`` (a name meant for the
    provider; the paper's tasks set their own), else, under every preset that encodes parameters, a
    neutral name, so a user's module, class, file or directory name never reaches a prompt. Presets
    that show raw parameters show the task's name."""
    if task.prompt_name:
        return task.prompt_name
    return NEUTRAL_TITLE if mechanisms.encode_params else task.name


def prompt_context(task: Task, settings: PromptSettings, codec: Codec) -> PromptContext:
    """The public context of every prompt (wire side): task text as the mechanisms allow, D, the box
    (encoded when the warm-up is drawn in the encoded space), digits, and the switches. Holds no secret.
    """
    m = settings.mechanisms
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
        param_range=None if m.encode_params else settings.box,
        optimum=optimum,
        component_notes=tuple((k, text.components.get(k, k)) for k in task.components if k not in codec.hidden_components),
        diagnostic_notes=tuple((k, text.diagnostics.get(k, k)) for k in diagnostics),
        decimals=settings.decimals,
        params_style=settings.params_style,
        param_digits=settings.param_digits,
        layout=settings.layout,
        title=prompt_title(task, m),
        history_limit=settings.top_k,
        param_encoding=param_words,
        reward_encoding=reward_words,
        warmup_range=warmup_box(settings.box, codec.warmup_scale) if (m.encoded_warmup and m.encode_params) else None,
        describe_task=m.describe_task,
        hidden=task.policy.hidden,
        activation="" if task.policy.is_linear else task.policy.activation,
        layer_ranges=None if m.encode_params or task.policy.is_linear else tuple(task.policy.layer_boxes(task.n_s, task.n_a, settings.box)),
        number_format=settings.number_format,
    )
