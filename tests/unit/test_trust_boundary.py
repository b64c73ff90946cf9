"""The wire package (everything that can reach the LLM) must not reach client-side code."""

from __future__ import annotations

import ast
from pathlib import Path

import ppprops.wire

WIRE = Path(ppprops.wire.__file__).parent
ALLOWED_STDLIB = {"__future__", "collections", "dataclasses", "functools", "importlib", "json", "math", "re", "string", "typing"}


def _imports(path: Path) -> list[tuple[str, int]]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, 0) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out.append((node.module or "", node.level))
    return out


def test_wire_imports_only_itself_and_the_standard_library() -> None:
    files = sorted(WIRE.rglob("*.py"))
    assert len(files) >= 6
    for f in files:
        for module, level in _imports(f):
            if level == 1:
                continue  # a sibling inside ppprops.wire
            assert level == 0, f"{f.name} reaches outside wire with a relative import ({'.' * level}{module})"
            assert module.split(".")[0] in ALLOWED_STDLIB, f"{f.name} imports {module}"


def test_the_check_catches_a_client_import(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("from ..client.secrets import Secrets\nimport numpy\n")
    found = _imports(bad)
    assert ("client.secrets", 2) in found and ("numpy", 0) in found
