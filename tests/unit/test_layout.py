"""The package's layout rules (docs/architecture.md): no import cycle, no private name across modules.

The import graph is read from the source with ``ast``: every ``import``/``from ... import`` of a
ppprops module, at module level, inside a function (a deferred import still makes the two modules
depend on each other) or under ``if TYPE_CHECKING:`` (a type-level import is a dependency too: a
loop of them is a knot of modules that cannot be understood apart). Importing a submodule is not
counted as importing its package's ``__init__``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src"
PACKAGE = "ppprops"


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement, wherever it is (module level, functions, ``if TYPE_CHECKING:``)."""
    return [node for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))]


def import_graph(root: Path, package: str) -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    """(module -> the package's modules it imports, [(importer, source module, private name)])."""
    files = {module_name(p, root): p for p in sorted((root / package).rglob("*.py"))}
    edges: dict[str, set[str]] = {m: set() for m in files}
    private: list[tuple[str, str, str]] = []
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        for node in _imports(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                edges[mod].update(a.name for a in node.names if a.name in files)
                continue
            if node.level:
                base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source not in files:
                continue
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                target = sub if sub in files else source
                if target != mod:
                    edges[mod].add(target)
                if target == source and alias.name.startswith("_") and not alias.name.startswith("__"):
                    private.append((mod, source, alias.name))
    return edges, private


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as [a, b, ..., a], or None (depth-first search with colours)."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(edges, WHITE)
    path: list[str] = []

    def visit(v: str) -> list[str] | None:
        colour[v] = GREY
        path.append(v)
        for w in sorted(edges[v]):
            if colour[w] == GREY:
                return path[path.index(w) :] + [w]
            if colour[w] == WHITE and (found := visit(w)):
                return found
        path.pop()
        colour[v] = BLACK
        return None

    for v in sorted(edges):
        if colour[v] == WHITE and (found := visit(v)):
            return found
    return None


def test_the_graph_sees_package_imports() -> None:
    edges, _ = import_graph(SRC, PACKAGE)
    assert "ppprops.methods" in edges["ppprops.strategies"]  # module level
    assert "ppprops.proposers.cmaes" in edges["ppprops.strategies"]  # deferred, inside a function
    assert "ppprops.evaluation" in edges["ppprops.proposers.base"]  # only under TYPE_CHECKING, counted too


def test_no_import_cycle_in_src() -> None:
    edges, _ = import_graph(SRC, PACKAGE)
    assert find_cycle(edges) is None, " -> ".join(find_cycle(edges) or [])


def test_no_private_name_imported_across_modules() -> None:
    _, private = import_graph(SRC, PACKAGE)
    assert private == [], [f"{m} imports {n} from {s}" for m, s, n in private]


@pytest.fixture
def toy_package(tmp_path: Path) -> Path:
    pkg = tmp_path / "toy"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import thing\n")
    (pkg / "b.py").write_text("def f():\n    from .sub.c import _hidden\n    return _hidden\nthing = 1\n")
    (pkg / "sub" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..a import x\n_hidden = 2\n")
    return tmp_path


def test_the_checks_can_fail(toy_package: Path) -> None:
    """A TYPE_CHECKING import closing a loop is a cycle, and so is a deferred one; ``_hidden`` is private."""
    edges, private = import_graph(toy_package, "toy")
    assert find_cycle(edges) == ["toy.a", "toy.b", "toy.sub.c", "toy.a"]
    assert private == [("toy.b", "toy.sub.c", "_hidden")]
    (toy_package / "toy" / "sub" / "c.py").write_text("_hidden = 2\n")
    edges, _ = import_graph(toy_package, "toy")
    assert find_cycle(edges) is None
    (toy_package / "toy" / "sub" / "c.py").write_text("def g():\n    from .. import a\n_hidden = 2\n")
    edges, _ = import_graph(toy_package, "toy")
    assert find_cycle(edges) == ["toy.a", "toy.b", "toy.sub.c", "toy.a"]


# The study is the composition root: it builds everything below it from the run's stored config and
# hands each layer the narrow settings it needs. These modules may take the whole RunConfig; no other.
RUN_CONFIG_USERS = {"config", "settings", "study", "rundir", "runner", "api", "cli", "study_commands"}
RUN_CONFIG_PACKAGES = ("experiments", "privacy", "baselines")  # grids, reports and the audit read stored runs whole


def test_no_module_below_the_study_takes_the_whole_run_config() -> None:
    users = set()
    for path in sorted((SRC / PACKAGE).rglob("*.py")):
        mod = module_name(path, SRC).removeprefix(f"{PACKAGE}.")
        for node in _imports(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("config") and any(a.name == "RunConfig" for a in node.names):
                users.add(mod)
    below = sorted(m for m in users if m not in RUN_CONFIG_USERS and not m.startswith(RUN_CONFIG_PACKAGES))
    assert below == [], f"modules below the study that import RunConfig: {below}"
    assert {"study", "runner", "api"} <= users  # the check sees the modules that do


# Sizes that hold the layout: the study is the composition root, not the place every feature lands
# (a new feature gets a module of its own), and no class grows into a second study.
STUDY_MAX_LINES = 500
CLASS_MAX_LINES = 450
# The study's modules: they call the proposers through ``proposers.base.SearchProposer``'s hooks,
# never by looking an ability up.
STUDY_MODULES = ("study", "env_loop", "told", "finalizing", "phases", "scheduling")


def class_sizes(root: Path, package: str) -> list[tuple[int, str]]:
    """(lines, "module.Class") of every class in the package, largest first (nested classes too)."""
    sizes = []
    for path in sorted((root / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                sizes.append((node.end_lineno - node.lineno + 1, f"{module_name(path, root)}.{node.name}"))  # type: ignore[operator]
    return sorted(sizes, reverse=True)


def ability_lookups(path: Path) -> list[str]:
    """Every ``getattr``/``hasattr`` call in a module, as "name:line"."""
    return [f"{node.func.id}:{node.lineno}" for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr")]


def test_the_study_and_every_class_stay_within_their_size() -> None:
    study = len((SRC / PACKAGE / "study.py").read_text(encoding="utf-8").splitlines())
    assert study <= STUDY_MAX_LINES, f"study.py is {study} lines (at most {STUDY_MAX_LINES}): give the feature a module of its own"
    sizes = class_sizes(SRC, PACKAGE)
    assert ("ppprops.study.Study" in {name for _, name in sizes}) and sizes[0][0] > 100  # the walk sees the classes
    over = [f"{name}: {lines} lines" for lines, name in sizes if lines > CLASS_MAX_LINES]
    assert over == [], f"classes over {CLASS_MAX_LINES} lines: {over}"


def test_the_study_looks_up_no_ability_of_a_proposer() -> None:
    found = {mod: ability_lookups(SRC / PACKAGE / f"{mod}.py") for mod in STUDY_MODULES}
    assert {mod: hits for mod, hits in found.items() if hits} == {}


def test_the_size_and_lookup_checks_can_fail(toy_package: Path) -> None:
    body = "".join(f"    def m{i}(self) -> int:\n        return {i}\n" for i in range(CLASS_MAX_LINES))
    (toy_package / "toy" / "big.py").write_text(f"class Big:\n{body}\n\nclass Small:\n    pass\n")
    assert class_sizes(toy_package, "toy")[:2] == [(1 + 2 * CLASS_MAX_LINES, "toy.big.Big"), (2, "toy.big.Small")]
    (toy_package / "toy" / "probe.py").write_text("def f(p):\n    return hasattr(p, 'ready') or getattr(p, 'rounds', False)\n")
    assert ability_lookups(toy_package / "toy" / "probe.py") == ["hasattr:2", "getattr:2"]
