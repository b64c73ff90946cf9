"""Making a task's environment from data: a Gymnasium id or an entry point, kwargs, a step limit, imports.

An ``EnvRecipe`` is what a run stores about its env, so another process (an evaluation worker,
``ppprops resume``, ``ppprops policy eval``, a grid) makes the same env without the user's
registration code having run. ``EnvRecipe.env_spec()`` turns it into Gymnasium's own ``EnvSpec``
(id, entry point string, kwargs, max_episode_steps), the form the policy file records, so the
deployed env and the searched env are made by one and the same ``gym.make`` call.

Everything that can fail while importing user code (a missing dependency, a SyntaxError, a module
that raises) is one ``TaskImportError`` line that names the real cause; an env whose constructor
raises is one ``EnvError`` line naming the user's exception and where in their code it was raised
(``describe_user_error``, which also words failures of ``reset`` / ``step`` for the episode loop).
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import os
import sys
import sysconfig
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from ..errors import ConfigError, MissingExtraError, UnknownTaskError

# Packages that register more Gymnasium ids when imported; tried only when an id is not found.
PLUGINS = ("highway_env", "gymnasium_robotics")


class TaskImportError(ConfigError):
    """A module a task needs (its env's module, an ``imports`` entry, a ``--gym-packages`` module) fails to import."""


class EnvError(ConfigError):
    """The env cannot be made: its constructor (or the entry point's import inside ``gym.make``) raised."""


def _library_roots() -> tuple[str, ...]:
    """Folders whose frames are not the user's code: ppprops, gymnasium, the standard library."""
    import gymnasium

    roots = {str(Path(__file__).resolve().parents[1]), str(Path(gymnasium.__file__).resolve().parent)}
    roots |= {str(Path(p).resolve()) for k, p in sysconfig.get_paths().items() if k in ("stdlib", "platstdlib")}
    return tuple(sorted(roots))


def _installed_roots() -> tuple[str, ...]:
    return tuple(sorted({str(Path(p).resolve()) for k, p in sysconfig.get_paths().items() if k in ("purelib", "platlib")}))


_GYM_WRAPPED = " was raised from the environment creator"  # gymnasium re-raises a constructor's TypeError with this


def _unwrapped(exc: BaseException) -> BaseException:
    """The exception itself, or the constructor's own TypeError that gymnasium's ``make`` wrapped (``from`` it)."""
    if _GYM_WRAPPED in str(exc) and exc.__cause__ is not None:
        return exc.__cause__
    return exc


def user_frame(exc: BaseException) -> traceback.FrameSummary | None:
    """The innermost frame where ``exc`` was raised in the user's code, else in a library that is not ppprops,
    gymnasium or the standard library (an installed env package); None when every frame is one of those.

    The frames of the exceptions ``exc`` was raised ``from`` count too, innermost last.
    """
    chain: list[BaseException] = []
    e: BaseException | None = exc
    while e is not None and len(chain) < 10:
        chain.append(e)
        e = e.__cause__
    # a cause's frames run from where its wrapper caught it inwards: they lie deeper than the wrapper's
    frames = [f for c in chain for f in traceback.extract_tb(c.__traceback__)]

    def outside(frame: traceback.FrameSummary, roots: tuple[str, ...]) -> bool:
        name = frame.filename
        if name.startswith("<"):  # <frozen importlib._bootstrap>, <string>
            return False
        path = str(Path(name).resolve())
        return not any(path == r or path.startswith(r + os.sep) for r in roots)

    library = _library_roots()
    for roots in (library + _installed_roots(), library):
        found = [f for f in frames if outside(f, roots)]
        if found:
            return found[-1]
    return None


def describe_user_error(exc: BaseException) -> str:
    """One line for an exception raised by a user's env (in its constructor, ``reset`` or ``step``).

    ``Type: first line of the message (at FILE:LINE, in FUNCTION)``, where the location is the
    innermost frame in the user's code (``user_frame``), left out when there is none; e.g.
    ``RuntimeError: motor driver fault (at /home/me/robot.py:42, in step)``. For the episode loop's
    mid-run failures and ``EnvRecipe.make``; never a traceback.
    """
    origin = _unwrapped(exc)
    text = str(origin).strip()
    first = text.splitlines()[0] if text else ""
    line = f"{type(origin).__name__}{': ' + first if first else ''}"
    frame = user_frame(exc)
    if frame is not None:
        line += f" (at {frame.filename}:{frame.lineno}, in {frame.name})"
    return line


def import_module(name: str, why: str = "") -> Any:
    """``importlib.import_module`` whose failures are one ConfigError line naming the real cause."""
    where = f" (needed by {why})" if why else ""
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # gymnasium-robotics prints an unrelated notice
            return importlib.import_module(name)
    except ModuleNotFoundError as e:
        missing = e.name or str(e)
        cwd = os.getcwd()
        if (name == missing or name.startswith(f"{missing}.")) and cwd not in sys.path and "" not in sys.path:
            sys.path.append(cwd)  # as `python -m` would: a module in the current folder (the console script lacks it)
            return import_module(name, why)
        if name == missing or name.startswith(f"{missing}."):
            raise TaskImportError(f"cannot import module {name!r}{where}: no such module on the Python path "
                                  "(install it, or run from the folder that holds it)") from None
        raise TaskImportError(f"importing module {name!r}{where} failed: it needs {missing!r}, which is not installed") from None
    except SyntaxError as e:
        raise TaskImportError(f"importing module {name!r}{where} failed: SyntaxError in {e.filename} line {e.lineno}: {e.msg}") from None
    except MissingExtraError:
        raise
    except Exception as e:  # the module itself raised while being imported
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise TaskImportError(f"importing module {name!r}{where} failed: {type(e).__name__}{': ' + first if first else ''}") from None


def add_paths(paths: tuple[str, ...]) -> None:
    """Append ``paths`` (folders of user env modules) to ``sys.path``, each once."""
    for p in paths:
        if p not in sys.path:
            sys.path.append(p)


def load_attr(ref: str, why: str = "") -> Any:
    """The object named ``module:attr`` (attr may be dotted: ``module:Class.method``)."""
    module, sep, attr = ref.partition(":")
    if not sep or not module or not attr:
        raise ConfigError(f"{ref!r} is not of the form module:name")
    obj = import_module(module, why)
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise ConfigError(f"module {module!r} has no {attr!r}{f' (needed by {why})' if why else ''}") from None
    return obj


def entry_point_of(fn: Callable[..., Any]) -> tuple[str, tuple[str, ...]] | None:
    """``("module:qualname", paths)`` from which another process imports ``fn``; None when it cannot.

    A class or function defined in the script being run (``__main__``) is named by the script's file,
    whose folder goes into ``paths``; a lambda, or anything defined inside a function, has no such name.
    """
    module = getattr(fn, "__module__", None)
    qualname = getattr(fn, "__qualname__", None)
    if not module or not qualname or "<" in qualname:
        return None
    if module in ("__main__", "__mp_main__"):
        main = sys.modules.get(module)
        spec = getattr(main, "__spec__", None)
        if spec is not None and spec.name and spec.name != "__main__":  # python -m package.script
            return f"{spec.name}:{qualname}", ()
        file = getattr(main, "__file__", None)
        if not file:
            return None  # an interactive session
        path = Path(file).resolve()
        return f"{path.stem}:{qualname}", (str(path.parent),)
    try:
        if load_attr(f"{module}:{qualname}") is not fn:
            return None
    except ConfigError:
        return None
    root = import_root(module)
    return f"{module}:{qualname}", (() if root is None else (root,))


def import_root(module: str) -> str | None:
    """The folder a user's module was imported from (its top package's parent), so another process can
    import it too; None for installed packages and the standard library, which every process finds."""
    import sysconfig

    mod = sys.modules.get(module)
    file = getattr(mod, "__file__", None)
    if not file:
        return None
    path = Path(file).resolve()
    depth = module.count(".") + (1 if path.name == "__init__.py" else 0)
    root = path.parents[depth]
    installed = {Path(p).resolve() for k, p in sysconfig.get_paths().items() if k in ("stdlib", "platstdlib", "purelib", "platlib")}
    if any(root == p or p in root.parents for p in installed):
        return None
    return str(root)


def _import_plugin(module: str) -> bool:
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            importlib.import_module(module)
    except ImportError:
        return False
    return True


def registered_id(name: str) -> str | None:
    """The Gymnasium id ``name`` refers to (exact, else case-insensitive), or None.

    ``module:Env-v0`` imports ``module`` first, as ``gym.make`` does; that module failing to import
    is an error naming the cause, never "unknown". A deprecated or missing version is Gymnasium's
    own one-line message (e.g. "use CliffWalking-v1 instead").
    """
    import gymnasium as gym

    module, sep, env_id = name.rpartition(":")
    if sep:
        import_module(module, name)
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
    if found is None:
        try:
            gym.spec(name)
        except (gym.error.DeprecatedEnv, gym.error.VersionNotFound) as e:
            raise UnknownTaskError(f"unknown task {name!r}: {e}") from None
        except gym.error.Error:
            pass
    return found


def known_ids() -> list[str]:
    """Every registered Gymnasium env id."""
    import gymnasium as gym

    return list(gym.registry)


def _registered_spec(env_id: str) -> Any:
    import gymnasium as gym

    module, sep, bare = env_id.rpartition(":")
    if sep:
        import_module(module, env_id)
        env_id = bare
    try:
        return gym.spec(env_id)
    except gym.error.Error as e:
        raise UnknownTaskError(f"{env_id} is not a registered Gymnasium id in this process ({e}); it was registered by "
                               "code that has not run here: import the module that registers it (imports / --gym-packages)") from None


class EnvRecipe(BaseModel):
    """How to make a task's env. Stored with every run and in every policy file (as part of its
    ``TaskSpec``, serialised by pydantic).

    ``id`` is a Gymnasium id (``"Ant-v5"``, ``"module:Env-v0"``) looked up when the env is made, or,
    with ``entry_point``, only a label. ``entry_point`` is ``"module:attr"``: an ``Env`` subclass or a
    function returning an env, called with ``kwargs``. ``max_episode_steps`` adds a ``TimeLimit``
    (for an id it overrides the registered limit). ``imports`` are modules imported first (packages
    that register ids, like rl-zoo3's ``--gym-packages``); ``paths`` are folders put on ``sys.path``
    first (the folder of a task file). ``setup`` is a ``module:function`` of ppprops' own that checks
    a simulator extra before the env is made.
    """

    model_config = ConfigDict(frozen=True, defer_build=True)

    id: str
    entry_point: str | None = None
    kwargs: dict[str, Any] = Field(default_factory=dict)
    max_episode_steps: int | None = None
    imports: tuple[str, ...] = ()
    paths: tuple[str, ...] = ()
    setup: str | None = None

    def local_only(self) -> str | None:
        """Why only this process can make the env, or None.

        That is the case for an id registered here with a factory that has no importable name (a
        lambda, a function defined inside another): other processes know neither the id nor the factory.
        """
        if self.entry_point is not None or ":" in self.id:
            return None
        import gymnasium as gym

        reg = gym.registry.get(self.id)
        if reg is None or isinstance(reg.entry_point, str) or reg.entry_point is None or entry_point_of(reg.entry_point) is not None:
            return None
        name = getattr(reg.entry_point, "__qualname__", repr(reg.entry_point))
        return (f"its env {self.id} is registered in this process with a factory that has no importable name ({name}), so "
                "no other process can make it: define the factory at the top level of a module")  # fmt: skip

    def prepare(self) -> None:
        """Run the setup check, extend ``sys.path``, import ``imports``; before any env is made."""
        if self.setup is not None:
            load_attr(self.setup, self.id)()
        add_paths(self.paths)
        for module in self.imports:
            import_module(module, self.id)

    def env_spec(self) -> Any:
        """Gymnasium's ``EnvSpec`` for this recipe (kwargs merged over a registered id's, limit applied)."""
        from gymnasium.envs.registration import EnvSpec

        self.prepare()
        if self.entry_point is not None:
            return EnvSpec(id=_label(self.id), entry_point=self.entry_point, kwargs=dict(self.kwargs),
                           max_episode_steps=self.max_episode_steps, disable_env_checker=True)  # fmt: skip
        reg = _registered_spec(self.id)
        steps = self.max_episode_steps if self.max_episode_steps is not None else reg.max_episode_steps
        return replace(reg, kwargs={**reg.kwargs, **dict(self.kwargs)}, max_episode_steps=steps, disable_env_checker=True)

    def make(self) -> Any:
        """A fresh env (made, not reset); every failure while making it is one ConfigError line.

        Raises:
            MissingExtraError: a simulator extra is missing (the message names the pip extra).
            TaskImportError: a module the env needs fails to import.
            EnvError: the constructor raised: ``making ID failed: Type: message (at FILE:LINE, in
                FUNCTION)`` with the innermost frame of the user's code (``describe_user_error``); a
                TypeError from the constructor's call itself (a missing or unknown keyword) ends
                ``(check env_kwargs)`` instead.
        """
        import gymnasium as gym

        spec = self.env_spec()
        try:
            return gym.make(spec)
        except gym.error.DependencyNotInstalled as e:
            if "mujoco" in str(e).lower():
                raise MissingExtraError("mujoco", self.id) from e
            raise EnvError(f"{self.id} needs a package that is not installed: {e}") from None
        except (ConfigError, MissingExtraError):
            raise
        except Exception as e:
            if isinstance(e, TypeError) and user_frame(e) is None:  # most often a keyword the constructor lacks or does not take
                cause = str(e).split(" was raised from the environment creator")[0]  # gymnasium's wrapping
                raise EnvError(f"making {self.id} failed: {cause} (check env_kwargs)") from None
            raise EnvError(f"making {self.id} failed: {describe_user_error(e)}") from None

    def pinned(self) -> EnvRecipe:
        """The same env with a registered id replaced by its entry point, kwargs and limit.

        A user's env registered by code that only runs in this process (``gym.register`` inside
        ``main()``) is then rebuilt elsewhere without that code. Registered entry points that are
        callables become ``module:qualname`` strings when they have one; otherwise the id stays (see
        ``local_only``).
        """
        if self.entry_point is not None:
            return self
        self.prepare()
        reg = _registered_spec(self.id)
        if reg.additional_wrappers or reg.entry_point is None:
            return self  # wrappers a plain entry point would lose: keep looking the id up
        kwargs = {**reg.kwargs, **dict(self.kwargs)}
        steps = self.max_episode_steps if self.max_episode_steps is not None else reg.max_episode_steps
        if isinstance(reg.entry_point, str):
            load_attr(reg.entry_point, self.id)  # imported here, so its folder is known
            root = import_root(reg.entry_point.split(":")[0])
            paths = self.paths if root is None else tuple(dict.fromkeys((*self.paths, root)))
            return self.model_copy(update={"entry_point": reg.entry_point, "kwargs": kwargs, "max_episode_steps": steps, "paths": paths})
        found = entry_point_of(reg.entry_point)
        if found is None:
            return self
        ref, paths = found
        update = {"entry_point": ref, "kwargs": kwargs, "max_episode_steps": steps, "paths": tuple(dict.fromkeys(self.paths + paths))}
        return self.model_copy(update=update)


@dataclass(frozen=True)
class Prepare:
    """``Task.setup`` of a declared task: ``recipe.prepare()`` as a value (equal recipes, equal setups)."""

    recipe: EnvRecipe

    def __call__(self) -> None:
        """Import, register and check what the env needs (``EnvRecipe.prepare``)."""
        self.recipe.prepare()


def _label(text: str) -> str:
    """A Gymnasium-valid id for an entry-point env (EnvSpec parses ids; the label is only a name)."""
    import re

    return re.sub(r"[^\w.-]", "_", text.split(":")[-1]) or "env"


def check_json_kwargs(kwargs: Mapping[str, Any], where: str) -> dict[str, Any]:
    """env kwargs are stored with the run: they must be JSON values."""
    try:
        return json.loads(json.dumps(dict(kwargs), allow_nan=False))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: env_kwargs must be JSON values (numbers, strings, booleans, lists, tables): {e}") from None


def has_time_limit(env: Any) -> bool:
    """True when the env is wrapped in a TimeLimit (an episode then always ends)."""
    from gymnasium.wrappers import TimeLimit

    e = env
    while e is not None:
        if isinstance(e, TimeLimit):
            return True
        e = getattr(e, "env", None)
    return False
