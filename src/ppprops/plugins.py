"""Plugins: installed packages that add methods or privacy attacks in every process.

``methods.register_method`` and ``privacy.attacks.register_attack`` change the registry of the
process that calls them. A run read back in another process (``ppprops show``, ``audit``,
``ppprops.load_run``), a run of an experiment grid (a fresh interpreter per run, or a Ray worker)
and a shell's ``ppprops run`` know a method only if that process registers it too. A package makes
its registrations known everywhere by declaring an entry point in the group ``ppprops.plugins``
(docs/architecture.md has the ``pyproject.toml`` lines)::

    [project.entry-points."ppprops.plugins"]
    shrink = "my_package.ppprops_plugin"

The value names a module (importing it registers) or ``module:function`` (called with no
argument after the import). ``load_plugins`` loads every entry point of the group once per
process; the registries call it the first time a lookup misses (an unknown method name, a full
listing of the ``--method`` choices, ``privacy.attacks.run_attacks``: the privacy report and the
audit's exposure check), so a process that never asks for anything beyond the built-in ones never
scans the installed packages.
"""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points
from types import ModuleType

from .errors import ConfigError

GROUP = "ppprops.plugins"

_loaded = False
_failure: str | None = None  # a plugin that failed once fails every later lookup the same way


def load_plugins() -> None:
    """Load every entry point of the group ``ppprops.plugins`` (``GROUP``), once per process.

    Every plugin is tried; the first that fails to import, or whose function raises, is reported.
    Later calls return at once, or raise the same error again (a plugin that failed halfway is not
    imported twice).

    Raises:
        ConfigError: one line naming the entry point, its value, the distribution that declares it
            and the plugin's own error (``ppprops`` prints it and exits 2).
    """
    global _loaded, _failure
    if not _loaded:
        _loaded = True  # set first: a plugin that looks a method up while it loads does not load itself again
        for ep in entry_points(group=GROUP):
            try:
                _load(ep)
            except ConfigError as e:
                _failure = _failure or str(e)
    if _failure is not None:
        raise ConfigError(_failure)


def _load(ep: EntryPoint) -> None:
    try:
        obj = ep.load()
        if callable(obj) and not isinstance(obj, ModuleType):
            obj()
    except Exception as e:  # the plugin's code, whatever it raises, is the plugin's fault: one line naming it
        detail = (str(e).strip().splitlines() or [""])[0]
        what = f"{type(e).__name__}: {detail}" if detail else type(e).__name__
        name, version = _distribution(ep)
        source = f"{name} {version}" if name else "a package"
        fix = f"fix it or uninstall {name}" if name else "fix it or remove the package that declares it"
        raise ConfigError(f"plugin {ep.name!r} = {ep.value!r} (entry point group {GROUP!r} of {source}) failed to load: "
                          f"{what}; {fix}") from None  # fmt: skip


def _distribution(ep: EntryPoint) -> tuple[str | None, str]:
    """The name and version of the package that declares ``ep`` (None when unknown)."""
    dist = ep.dist
    if dist is None:
        return None, ""
    return dist.metadata["Name"] or None, dist.version or ""
