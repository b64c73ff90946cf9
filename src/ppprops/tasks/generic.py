"""Tasks built on the fly for any Gymnasium id that ppprops has no description of.

The observation is flattened (Box observations only), the action space decides continuous or
discrete, the return is the env's own. Info keys can be declared as reward components (summed over
the episode) or diagnostics (last value). The prose comes from ``descriptions/generic.toml``.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import tomllib
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

import numpy as np

from ..errors import ConfigError, MissingExtraError, UnknownTaskError
from .base import ComponentSums, FlatBox, Task, TaskText

_TEXT = "ppprops.tasks.descriptions"
# Packages that register more Gymnasium ids when imported; tried only when an id is not found.
PLUGINS = ("highway_env", "gymnasium_robotics")


@dataclass(frozen=True)
class GenericFeedback(ComponentSums):
    """ComponentSums that marks a task as generic, so worker processes can rebuild it from its spec."""


@dataclass(frozen=True)
class GenericSpec:
    """Everything needed to rebuild a generic task in another process."""

    env_id: str
    components: tuple[str, ...] = ()
    diagnostics: tuple[str, ...] = ()


def _import_plugin(module: str) -> bool:
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # gymnasium-robotics prints an unrelated notice
            importlib.import_module(module)
    except ImportError:
        return False
    return True


def registered_id(name: str) -> str | None:
    """The Gymnasium id ``name`` refers to (exact, else case-insensitive), or None.

    ``module:Env-v0`` imports ``module`` first, as ``gym.make`` does.
    """
    import gymnasium as gym

    module, sep, env_id = name.rpartition(":")
    if sep:
        if not _import_plugin(module):
            return None
        return name if env_id in gym.registry else None

    def lookup() -> str | None:
        if name in gym.registry:
            return name
        folded = [k for k in gym.registry if k.lower() == name.lower()]
        return folded[0] if len(folded) == 1 else None

    found = lookup()
    if found is None:
        for plugin in PLUGINS:
            if _import_plugin(plugin) and (found := lookup()) is not None:
                break
    return found


def known_ids() -> list[str]:
    import gymnasium as gym

    return list(gym.registry)


def _fmt(v: float) -> str:
    return f"{v:g}"


def _bounds(template: str, low: float, high: float) -> str:
    return template.format(low=_fmt(low), high=_fmt(high)) if np.isfinite(low) and np.isfinite(high) else ""


def _make(env_id: str) -> Any:
    import gymnasium as gym

    try:
        return gym.make(env_id, disable_env_checker=True)
    except gym.error.DependencyNotInstalled as e:
        if "mujoco" in str(e).lower():
            raise MissingExtraError("mujoco", env_id) from e
        raise ConfigError(f"{env_id} needs a package that is not installed: {e}") from e


def _spaces(env_id: str) -> tuple[Any, Any]:
    from gymnasium import spaces

    env = _make(env_id)
    try:
        obs_space, act_space = env.observation_space, env.action_space
    finally:
        env.close()
    if isinstance(obs_space, spaces.Dict):
        raise ConfigError(
            f"{env_id} has a Dict observation ({', '.join(obs_space.spaces)}); a generic task cannot choose "
            "which parts the policy sees: it needs an explicit observation adapter (a registered ppprops task)"
        )
    if not isinstance(obs_space, spaces.Box):
        raise ConfigError(
            f"{env_id} has a {type(obs_space).__name__} observation; a generic task handles Box observations "
            "only: it needs an explicit observation adapter (a registered ppprops task)"
        )
    if isinstance(act_space, spaces.Discrete):
        if int(act_space.start) != 0:
            raise ConfigError(f"{env_id}: Discrete actions starting at {act_space.start} are not supported")
    elif not (isinstance(act_space, spaces.Box) and len(act_space.shape) == 1):
        raise ConfigError(f"{env_id}: only 1-D Box or Discrete action spaces are supported, got {act_space}")
    return obs_space, act_space


def _text(env_id: str, obs_space: Any, act_space: Any, components: tuple[str, ...], diagnostics: tuple[str, ...]) -> TaskText:
    raw = tomllib.loads(resources.files(_TEXT).joinpath("generic.toml").read_text(encoding="utf-8"))
    discrete = not hasattr(act_space, "low")
    n_s = int(np.prod(obs_space.shape))
    n_a = int(act_space.n) if discrete else int(act_space.shape[0])
    lows, highs = np.asarray(obs_space.low, dtype=float).reshape(-1), np.asarray(obs_space.high, dtype=float).reshape(-1)
    observations = tuple(raw["observation"].format(index=i, bounds=_bounds(raw["bounds"], lows[i], highs[i])) for i in range(n_s))
    if discrete:
        actions = tuple(raw["action_discrete"].format(index=j) for j in range(n_a))
    else:
        a_lo, a_hi = np.asarray(act_space.low, dtype=float), np.asarray(act_space.high, dtype=float)
        actions = tuple(
            raw["action_continuous"].format(index=j, bounds=_bounds(raw["bounds"], a_lo[j], a_hi[j])) for j in range(n_a)
        )
    return TaskText(
        summary=raw["summary"].format(env_id=env_id, n_s=n_s, n_a=n_a).strip(),
        observations=observations,
        actions=actions,
        reward_structure=raw["reward_structure"].strip(),
        reward_hint=raw["reward_hint"].strip(),
        hints=raw.get("hints", "").strip(),
        components={k: raw["component"].format(key=k) for k in components},
        diagnostics={**raw["diagnostics"], **{k: raw["diagnostic"].format(key=k) for k in diagnostics}},
    )


def generic_task(
    env_id: str, components: tuple[str, ...] | list[str] = (), diagnostics: tuple[str, ...] | list[str] = ()
) -> Task:
    """A Task for any registered Gymnasium id with a Box observation and Box/Discrete actions.

    ``components`` are info keys summed over an episode and reported as reward components (they are
    scaled with the return under PP-ProPS, so declare only reward-valued keys); ``diagnostics`` are
    info keys reported as their last value, never scaled.
    """
    return _generic(env_id, tuple(components), tuple(diagnostics))


@cache
def _generic(name: str, components: tuple[str, ...], diagnostics: tuple[str, ...]) -> Task:
    clash = set(components) & set(diagnostics)
    if clash or "episode_length" in diagnostics:
        raise ConfigError(f"info key(s) declared twice or reserved: {', '.join(sorted(clash) or ['episode_length'])}")
    env_id = registered_id(name)
    if env_id is None:
        raise UnknownTaskError(f"unknown task {name!r}: not a registered Gymnasium id")
    obs_space, act_space = _spaces(env_id)
    text = _text(env_id, obs_space, act_space, components, diagnostics)
    discrete = not hasattr(act_space, "low")
    n_s = len(text.observations)
    return Task(
        name=env_id,
        env_id=env_id,
        n_s=n_s,
        n_a=len(text.actions),
        action_type="discrete" if discrete else "continuous",
        observation=FlatBox(names=tuple(f"obs_{i}" for i in range(n_s))),
        feedback=GenericFeedback(keys=components, diagnostic_keys=diagnostics),
        text=text,
        components=components,
        diagnostics=("episode_length", *diagnostics),
        optimal_return=None,
    )


def spec_of(task: Task) -> GenericSpec | None:
    """The rebuild recipe of a generic task; None for any other task."""
    fb = task.feedback
    if not isinstance(fb, GenericFeedback):
        return None
    return GenericSpec(task.env_id, tuple(fb.keys), tuple(fb.diagnostic_keys))
