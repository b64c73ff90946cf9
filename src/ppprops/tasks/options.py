"""How a user names a task and the options of a task that is not a paper task (``TaskOptions``).

One object carries them everywhere: the ``--env`` / ``--task-file`` flags and their options
(``ppprops.settings`` derives the flags from its fields), ``ppprops.search``'s ``task_options``
mapping, ``ppprops.tasks.load_task`` / ``check_task`` and ``TaskSpec.with_options``.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field
from pydantic.dataclasses import dataclass

from ..policy import PolicySpec, parse_policy
from ..schema import SCHEMA, Flag, Int, JsonObject, Names, one_line_errors

__all__ = ["POLICY_OPTIONS", "TASK_OPTIONS", "TaskOptions"]


def _policy(value: Any) -> PolicySpec | None:
    """``--policy``'s value (``linear``, ``mlp:16,16``), a mapping or a PolicySpec; ValueError with one line."""
    return None if value is None else parse_policy(value)


@one_line_errors
@dataclass(frozen=True, config=SCHEMA)
class TaskOptions:
    """How a user names the task of a run: ``--env`` or ``--task-file``, and the options of a task
    that is not a paper task (``TASK_OPTIONS``). ``ppprops.tasks.load_task(options=...)`` turns them
    into the ``Task`` whose name and declaration (``task_spec``) the RunConfig stores. The one object
    that carries those options: ``load_task`` / ``check_task`` and ``TaskSpec.with_options`` take
    it, and ``ppprops.search``'s ``task_options`` mapping becomes one.

    Raises:
        ConfigError: on construction, for a value of the wrong type.
    """

    env: Annotated[str | None, Flag(
        "task name (see `ppprops envs`), a Gymnasium id, module:EnvId, or module:attr (an env class or factory)")] = None
    task_file: Annotated[Path | None, Flag(
        "a task described in TOML (env, observation, feedback keys, prose; docs/own-robot.md) instead of --env",
        metavar="FILE")] = None
    env_kwargs: Annotated[JsonObject, Flag("keyword arguments of the env's constructor, as a JSON object", metavar="JSON")] = None
    max_episode_steps: Annotated[Int | None, Field(ge=1), Flag(
        "time limit of an episode (needed when the env has none of its own)", metavar="N")] = None
    gym_packages: Annotated[tuple[str, ...], Flag(
        "a module to import first, e.g. one that registers the env (repeatable)", metavar="MOD", repeatable=True)] = ()
    obs_keys: Annotated[Names, Flag("a Dict observation: the entries the policy sees, in this order", metavar="K1,K2")] = None
    components: Annotated[tuple[str, ...], Flag(
        "an info key to sum as a reward component (repeatable); KEY.SUB picks an entry of a dict, KEY.* all",
        name="component", metavar="KEY", repeatable=True, api_name="components")] = ()
    diagnostics: Annotated[tuple[str, ...], Flag(
        "an info key to report as a diagnostic (its last value; repeatable)", name="diagnostic", metavar="KEY",
        repeatable=True, api_name="diagnostics")] = ()
    # The policy family (ppprops.policy.PolicySpec): applies to every task, the paper's too (it is not a
    # TASK_OPTIONS entry of has_options); None keeps the task's declared family (linear unless its file says).
    policy: Annotated[PolicySpec | None, BeforeValidator(_policy), Flag(
        "policy family: linear (the paper's u = W^T s + b) or mlp:H1[,H2,...], hidden layers of these widths "
        "(docs/policies.md)", metavar="linear|mlp:H1,H2", default_text="the task's; linear")] = None
    activation: Annotated[Literal["tanh", "relu"] | None, Flag(
        "activation of an mlp policy's hidden layers", default_text="tanh")] = None

    @property
    def has_options(self) -> bool:
        """True when an option of a task that is not a paper task is set (one of ``TASK_OPTIONS``)."""
        return bool(self.env_kwargs or self.max_episode_steps is not None or self.gym_packages or self.obs_keys is not None
                    or self.components or self.diagnostics)  # fmt: skip


# The options of a task that is not a paper task: the fields of TaskOptions but the two naming the task.
TASK_OPTIONS: tuple[str, ...] = tuple(f.name for f in fields(TaskOptions) if f.name not in ("env", "task_file", "policy", "activation"))
# The options that choose the policy family: for every task (``tasks.load_task`` applies them last).
POLICY_OPTIONS: tuple[str, ...] = ("policy", "activation")
