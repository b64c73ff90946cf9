"""The ``ppprops task`` subcommands: ``task check`` runs the one zero-policy episode a user asks for.

Kept here so the main CLI only registers them (``add_task_commands(sub, parser_class)`` and
``TASK_HANDLERS``); errors are ``PPPropsError``s, which the main CLI turns into one line on stderr
and exit code 2. The task flags mirror ``ppprops run``'s (``--env``, ``--task-file``,
``--env-kwargs``, ``--max-episode-steps``, ``--gym-packages``, ``--obs-keys``, ``--component``,
``--diagnostic``) and mean the same; their values are checked by ``load_task``'s rules.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import ConfigError


def _json_object(text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object such as '{{\"g\": 9.81}}', got {text!r}")
    return value


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",")]
    if not all(names):
        raise argparse.ArgumentTypeError(f"expected names separated by commas, got {text!r}")
    return names


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n


def _policy(text: str) -> Any:
    from ..policy import parse_policy

    try:
        return parse_policy(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _seed(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = -1
    if not 0 <= n < 2**32:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^32), got {text!r}")
    return n


def add_task_commands(sub: argparse._SubParsersAction, parser_class: type[argparse.ArgumentParser]) -> None:  # type: ignore[type-arg]
    """Add the ``task`` parser (with ``task check``) to the main CLI's subparsers ``sub``."""
    from .check import PROBE_STEPS

    task = sub.add_parser("task", help="work with a task: check a task file or env before a run")
    tsub = task.add_subparsers(dest="task_command", required=True, parser_class=parser_class)
    ck = tsub.add_parser("check", help="run one zero-policy episode and report every problem of the task's declaration "
                                       "(loading a task never steps its env)")  # fmt: skip
    ck.add_argument("file", type=Path, nargs="?", default=None, help="a task file (or give --env / --task-file)")
    ck.add_argument("--env", default=None, help="task name, Gymnasium id, module:EnvId, or module:attr (as for `ppprops run`)")
    ck.add_argument("--task-file", type=Path, default=None, metavar="FILE", help="a task file (as for `ppprops run`)")
    ck.add_argument("--env-kwargs", type=_json_object, default=None, metavar="JSON",
                    help="keyword arguments of the env's constructor, as a JSON object")  # fmt: skip
    ck.add_argument("--max-episode-steps", type=_positive, default=None, metavar="N", help="time limit of an episode")
    ck.add_argument("--gym-packages", action="append", default=[], metavar="MOD", help="a module to import first (repeatable)")
    ck.add_argument("--obs-keys", type=_names, default=None, metavar="K1,K2", help="a Dict observation: the entries the policy sees")
    ck.add_argument("--component", dest="components", action="append", default=[], metavar="KEY",
                    help="an info key summed as a reward component (repeatable); KEY.* lists every entry of a dict")  # fmt: skip
    ck.add_argument("--diagnostic", dest="diagnostics", action="append", default=[], metavar="KEY",
                    help="an info key reported as a diagnostic (repeatable)")  # fmt: skip
    ck.add_argument("--policy", type=_policy, default=None, metavar="linear|mlp:H1,H2",
                    help="policy family, as for `ppprops run`: the report says its D")  # fmt: skip
    ck.add_argument("--activation", choices=("tanh", "relu"), default=None, help="activation of an mlp policy")
    ck.add_argument("--seed", type=_seed, default=0, help="seed of the episode's reset (default 0)")
    ck.add_argument("--max-steps", type=_positive, default=PROBE_STEPS,
                    help=f"longest episode checked; an env with no time limit must end within it (default {PROBE_STEPS})")  # fmt: skip
    ck.add_argument("--json", action="store_true", help="one JSON object on stdout")


def cmd_task(a: argparse.Namespace) -> int:
    """``ppprops task check``: print the report; 0 when the episode found no problem, 1 when it found some.

    Raises:
        ConfigError: no task or two, or what stops the check before the episode (``check_task``).
    """
    from . import check_task
    from .options import POLICY_OPTIONS, TASK_OPTIONS, TaskOptions

    given = [x for x in (a.file, a.env, a.task_file) if x is not None]
    if len(given) != 1:
        raise ConfigError("task check needs one task: a task file, --env ID or --task-file FILE")
    file = a.file if a.file is not None else a.task_file
    options = TaskOptions(env=a.env, task_file=file, **{name: getattr(a, name) for name in (*TASK_OPTIONS, *POLICY_OPTIONS)})  # the flags' dests
    result = check_task(options=options, seed=a.seed, max_steps=a.max_steps)
    task = result.checked
    if a.json:
        out = result.to_json()
        if task is not None:
            out.update(policy=task.policy.to_json(), D=task.D)
        print(json.dumps(out))
    else:
        lines = result.lines()
        if task is not None and not task.policy.is_linear:  # a linear task's report is as before
            lines.append(f"  policy {task.policy.label()}: D = {task.D} parameters ({task.n_s} observations, {task.n_a} actions)")
        print("\n".join(lines))
    return 0 if result.ok else 1


TASK_HANDLERS: dict[str, Callable[[argparse.Namespace], int]] = {"task": cmd_task}

__all__ = ["TASK_HANDLERS", "add_task_commands", "cmd_task"]
