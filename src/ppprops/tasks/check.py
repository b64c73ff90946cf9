"""The explicit task check: one zero-policy episode that reports every problem of a declaration.

Loading a task never steps its env (on a real robot a step is a motion). The checks that need a
step run in the episodes of the run itself (``feedback.InfoFeedback``, ``evaluation.run_episode``)
and stop it at the first problem; this check runs them when the user asks for it
(``ppprops.tasks.check_task``, ``ppprops task check FILE | --env ID``), before a run, and reports
all of them at once:

- the env resets and steps without raising (a failure is one line naming the user's exception
  and where in their code: ``envs.describe_user_error``);
- what reset and every step return is well-formed: the observation fits the declared space, the
  reward is a number, the flags are booleans, the info a dict (``outputs.OutputCheck``, the line a
  run would stop with);
- the observation adapter gives n_s values;
- each declared component is in the env's info at the first step, each diagnostic at some step,
  every one a number (a dict names its entries, so ``KEY.*`` is expanded into them here and only
  here);
- an env with no time limit ends the episode within ``max_steps`` steps;
- a task's ``recorder`` (the paper's tasks) takes every step and the end without raising.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigError
from .base import Task
from .envs import describe_user_error, has_time_limit, load_attr, user_frame
from .feedback import MISSING, FeedbackKeyError, InfoKey, check_value, lookup, missing_key
from .outputs import OutputCheck, call_line
from .spec import Declared, TaskSpec, build_task, finish_spec, resolve_spaces

PROBE_STEPS = 10_000  # longest check episode of an env with no time limit


@dataclass(frozen=True)
class TaskCheck:
    """What one check episode found (``check_spec``).

    ``problems`` are one line each, worded as a run would stop with them; ``steps`` the steps
    taken; ``ended`` whether the episode ended (terminated or truncated) within ``max_steps``;
    ``expanded`` maps each ``KEY.*`` declared to the names it stands for; ``checked`` is the task
    as checked (``KEY.*`` expanded), ready for a run, or None when there are problems. A task
    without env has nothing to simulate: ``has_env`` False, no steps, no problems.
    """

    task: str
    has_env: bool
    seed: int
    max_steps: int
    problems: tuple[str, ...] = ()
    steps: int = 0
    ended: bool = False
    time_limit: bool = False
    raised: bool = False  # the env's reset or a step raised (``problems`` says what and where)
    malformed: bool = False  # the env's reset or a step returned a malformed value (``problems`` says which)
    expanded: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    kinds: Mapping[str, str] = field(default_factory=dict)  # "component" or "diagnostic", per key of ``expanded``
    checked: Task | None = field(default=None, compare=False, repr=False)

    @property
    def ok(self) -> bool:
        """True when the episode found no problem."""
        return not self.problems

    def lines(self) -> list[str]:
        """The report as lines of text (``ppprops task check``)."""
        if not self.has_env:
            return [f"task {self.task}: no env (a robot outside Python, driven with ask/tell); the declaration is valid "
                    "and there is nothing to simulate"]  # fmt: skip
        how = "ended" if self.ended else "the env raised" if self.raised else \
            "the env returned a malformed value" if self.malformed else \
            f"stopped after {self.steps} steps without ending" if self.time_limit else "did not end"  # fmt: skip
        head = f"task {self.task}: one zero-policy episode (seed {self.seed}): {self.steps} steps, {how}"
        out = [f"{head}; {len(self.problems)} problem{'s' if len(self.problems) != 1 else ''}:" if self.problems else f"{head}; no problem"]
        out += [f"  {p}" for p in self.problems]
        for key, names in self.expanded.items():
            flag = f"--{self.kinds.get(key, 'component')}"
            out.append(f"  {key} is {', '.join(names) or 'empty'} ({' '.join(f'{flag} {n}' for n in names)})")
        return out

    def to_json(self) -> dict[str, Any]:
        """The report as JSON values."""
        return {"task": self.task, "has_env": self.has_env, "ok": self.ok, "problems": list(self.problems), "steps": self.steps,
                "ended": self.ended, "time_limit": self.time_limit, "raised": self.raised, "malformed": self.malformed, "seed": self.seed,
                "max_steps": self.max_steps, "expanded": {k: list(v) for k, v in self.expanded.items()}}  # fmt: skip


def check_spec(spec: TaskSpec, *, seed: int = 0, max_steps: int = PROBE_STEPS) -> TaskCheck:
    """Check a declaration in one zero-policy episode (theta = 0) on its env, reset with ``seed``.

    Makes the env (reading its spaces when the declaration is not complete), runs at most
    ``max_steps`` steps and closes it. A task without env is validated without any episode.

    Raises:
        ConfigError: what stops the check before the episode: the env cannot be made, its spaces
            disagree with the declaration (one line, as when the task is loaded).
    """
    if spec.env is None:
        task = build_task(spec)
        return TaskCheck(task=spec.name, has_env=False, seed=seed, max_steps=max_steps, checked=task)
    recipe = spec.env if spec.complete else spec.env.pinned()
    env = recipe.make()
    try:
        if not spec.complete:
            spec = resolve_spaces(spec.model_copy(update={"env": recipe}), env)
        try:
            return _episode(spec, env, seed, max_steps)
        except ConfigError:
            raise
        except Exception as e:  # whatever else goes wrong with the user's env: a problem line, never a traceback
            return TaskCheck(task=spec.name, has_env=True, seed=seed, max_steps=max_steps, raised=True,
                             problems=(f"{spec.name}: the check stopped: {describe_user_error(e)}",))
    finally:
        try:
            env.close()
        except Exception:
            pass  # a close that fails says nothing about the declaration


def _episode(spec: TaskSpec, env: Any, seed: int, max_steps: int) -> TaskCheck:
    from ..policy import LinearPolicy

    name = spec.name
    problems: list[str] = []
    adapter = spec.observation.selection()
    n_s, n_a = len(spec.observation.names), len(spec.actions)
    space = env.action_space
    policy = LinearPolicy.from_flat(np.zeros((n_s + 1) * n_a), n_s, n_a, discrete=spec.action_type == "discrete",
                                    low=getattr(space, "low", None), high=getattr(space, "high", None))  # fmt: skip
    limited = has_time_limit(env)
    recorder = load_attr(spec.recorder, f"task {name}")() if spec.recorder is not None else None
    by_info = spec.recorder is None  # a recorder reads the info itself: nothing declared to check
    components = [c for c in spec.components if c.info is not None] if by_info else []
    diagnostics = [d for d in spec.diagnostics if d.info is not None] if by_info else []
    result = functools.partial(TaskCheck, task=name, has_env=True, seed=seed, max_steps=max_steps, time_limit=limited)
    hint = _kwargs_hint(spec)
    output = OutputCheck(env, adapter.keys)
    try:
        returned = env.reset(seed=seed)
    except Exception as e:
        problem = f"{name}: the env's reset raised {describe_user_error(e)}{hint(e)}"
        return result(problems=(problem,), raised=True)
    wrong = output.reset(returned)
    if wrong is not None:
        return result(problems=(call_line(name, "reset", seed, wrong),), malformed=True)
    obs, info = returned
    if adapter(obs).shape != (n_s,):
        problems.append(f"{name}: the observation adapter gives {adapter(obs).shape[0]} values, not {n_s}")
        return result(problems=tuple(problems))
    if not np.all(np.isfinite(adapter(obs))):
        return result(problems=(_non_finite(name, "reset", seed, "observation", adapter(obs)),))
    expanded: dict[str, tuple[str, ...]] = {}
    kinds: dict[str, str] = {}
    bad: set[str] = set()
    seen: set[str] = set()
    step, ended, raised, malformed = 0, False, False, False
    terminated = truncated = False
    while step < max_steps:
        try:
            returned = env.step(policy.act(adapter(obs)))
        except Exception as e:
            problems.append(f"{name}: the env's step {step + 1} raised {describe_user_error(e)}{hint(e)}")
            raised = True
            break
        wrong = output.step(returned)
        if wrong is not None:
            problems.append(call_line(name, f"step {step + 1}", seed, wrong))
            malformed = True
            break
        obs, reward, terminated, truncated, info = returned
        step += 1
        non_finite = [_non_finite(name, f"step {step}", seed, what, value) for what, value in (("reward", reward), ("observation", adapter(obs)))
                      if not np.all(np.isfinite(np.asarray(value, dtype=np.float64)))]  # fmt: skip
        if non_finite:  # where a run's episode ends too
            problems.extend(non_finite)
            break
        if step == 1:
            components = _expand(name, "component", components, info, problems, expanded)
            diagnostics = _expand(name, "diagnostic", diagnostics, info, problems, expanded)
            kinds.update({d.info: kind for kind, declared in (("component", spec.components), ("diagnostic", spec.diagnostics))
                          for d in declared if d.wildcard and d.info in expanded})
        for kind, declared in (("component", components), ("diagnostic", diagnostics)):
            for d in declared:
                if d.name in bad:
                    continue
                assert d.info is not None
                key = InfoKey(d.name, d.info)
                where = "at the first step" if step == 1 else f"at step {step}"
                try:
                    value = check_value(name, kind, key, info, where=where)
                except FeedbackKeyError as e:
                    problems.append(str(e))
                    bad.add(d.name)
                    continue
                if value is not None:
                    seen.add(d.name)
                elif kind == "component" and step == 1:
                    problems.append(str(missing_key(name, kind, key, info, where=where)))
                    bad.add(d.name)
        if recorder is not None:
            try:
                recorder.step(obs, float(reward), info)
            except Exception as e:
                problems.append(f"{name}: its recorder {spec.recorder} raised {describe_user_error(e)} at step {step}")
                recorder = None
        if terminated or truncated:
            ended = True
            break
    if not ended and not raised and not malformed and not limited and step >= max_steps:
        problems.append(f"task {name}: an episode of {spec.env.id if spec.env else name} did not end within {max_steps} steps "
                        "and the env has no time limit: give one with --max-episode-steps N (max_episode_steps in a task file)")  # fmt: skip
    if ended:
        for d in diagnostics:
            if d.name not in seen and d.name not in bad:
                assert d.info is not None
                problems.append(str(missing_key(name, "diagnostic", InfoKey(d.name, d.info), info, where="at any step of an episode")))
        if recorder is not None:
            try:
                recorder.finish(terminated=bool(terminated), truncated=bool(truncated), steps=step, info=info)
            except Exception as e:
                problems.append(f"{name}: its recorder {spec.recorder} raised {describe_user_error(e)} at the end of the episode")
    checked = None
    if not problems:
        if by_info and expanded:
            computed = tuple(d for d in spec.diagnostics if d.info is None)
            spec = spec.model_copy(update={"components": tuple(components), "diagnostics": (*computed, *diagnostics)})
        checked = build_task(spec if spec.complete else finish_spec(spec))
    return result(problems=tuple(problems), steps=step, ended=ended, raised=raised, malformed=malformed, expanded=expanded,
                  kinds=kinds, checked=checked)


def _non_finite(name: str, call: str, seed: int, what: str, value: Any) -> str:
    """The line for a NaN or infinite observation or reward in the probe episode: a run ends such an
    episode there (diagnostic ``numerical_fault``) and keeps it out of the prompt, so every candidate
    would be judged on a cut episode."""
    shown = np.array2string(np.asarray(value, dtype=np.float64), precision=4, threshold=8)
    return (f"{name}: the env's {call} (episode seed {seed}) returned a non-finite {what} {shown}; a run ends each "
            "such episode there and keeps it out of the prompt")


def _kwargs_hint(spec: TaskSpec) -> Callable[[BaseException], str]:
    """A hint for an exception raised outside the user's code by an env made with keyword arguments: check them."""
    kwargs = dict(spec.env.kwargs) if spec.env is not None else {}

    def hint(e: BaseException) -> str:
        return f" (check env_kwargs {json.dumps(kwargs)})" if kwargs and user_frame(e) is None else ""

    return hint


def _expand(task: str, kind: str, declared: list[Declared], info: Mapping[str, Any], problems: list[str],
            expanded: dict[str, tuple[str, ...]]) -> list[Declared]:  # fmt: skip
    """``declared`` with each ``KEY.*`` replaced by one entry per key of the dict ``info[KEY]`` (a problem when it is not one)."""
    out: list[Declared] = []
    for d in declared:
        if not d.wildcard:
            out.append(d)
            continue
        assert d.info is not None
        parent = d.info[:-2]
        value = lookup(info, parent)
        if value is MISSING:
            problems.append(str(missing_key(task, kind, InfoKey(d.name, parent), info, where="at the first step")))
            continue
        if not isinstance(value, Mapping):
            problems.append(f"{task}: {kind} {d.info!r} asks for the entries of {parent!r}, but that is a "
                            f"{type(value).__name__} in the env's info, not a dict")  # fmt: skip
            continue
        stem = d.name[:-2] if d.name.endswith(".*") else d.name
        entries = [Declared(name=f"{stem}.{k}", info=f"{parent}.{k}", reduce=d.reduce) for k in value]
        expanded[d.info] = tuple(e.name for e in entries)
        out.extend(entries)
    return out


__all__ = ["PROBE_STEPS", "TaskCheck", "check_spec"]
