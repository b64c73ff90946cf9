"""Every Python block of the README and of docs/ runs as written, unless its first line marks it a
fragment (``# fragment: <what it leaves out>``; docs/architecture.md, "Checks").

Each runnable block runs in a fresh Python process, in a folder that holds what the pages say a
reader has at hand: the example files (``examples/own_robot/*``, ``examples/robot_outside/robot.toml``)
and a ``best_policy.json``; the blocks of one page run in order in one folder, so a later block
finds what an earlier one wrote. No endpoint is needed: in these processes every LLM a study would
connect to, the embedded model or any ``base_url``, is the offline stand-in optimizer
(``ppprops.privacy.simulate.EchoOptimizer``), and the check that an endpoint answers before a run
starts (``ppprops.llm.probe``) passes, so a block keeps the method it shows (``pp``) and runs in
seconds. A block that runs its search under ``if __name__ == "__main__":`` runs as a
script (``__name__`` is ``"__main__"``), worker processes included.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(?:python|py)\n(.*?)^```", re.S | re.M)
FRAGMENT = re.compile(r"# fragment: \S")

HARNESS = textwrap.dedent('''
    import runpy, sys
    from unittest import mock
    from ppprops.privacy.simulate import EchoOptimizer

    with (mock.patch("ppprops.llm.client.connect", lambda llm, **kw: EchoOptimizer(llm, spread=0.5)),
          mock.patch("ppprops.llm.probe.probe_endpoint", lambda llm, api_key: None)):
        runpy.run_path(sys.argv[1], run_name="__main__")
''')


def python_blocks(page: Path) -> list[tuple[int, str]]:
    """(line, code) of every Python block of a page, in order."""
    text = page.read_text(encoding="utf-8")
    return [(text[: m.start()].count("\n") + 1, m.group(1)) for m in FENCE.finditer(text)]


def is_fragment(code: str) -> bool:
    """True when the block's first line marks it a fragment, with what it leaves out."""
    first = code.splitlines()[0] if code.strip() else ""
    return FRAGMENT.match(first) is not None


BLOCKS = [(page, line, code) for page in PAGES for line, code in python_blocks(page)]


def test_every_page_block_is_found_and_fragments_say_why() -> None:
    names = {f"{p.relative_to(ROOT)}:{line}" for p, line, _ in BLOCKS}
    assert any(n.startswith("README.md:") for n in names) and len(BLOCKS) >= 9
    for page, line, code in BLOCKS:
        first = code.splitlines()[0]
        if first.startswith("# fragment"):
            assert is_fragment(code), f"{page.name}:{line}: a fragment says what it leaves out: '# fragment: ...'"


def test_the_readmes_first_block_shows_the_top_level_keywords() -> None:
    first = next(code for page, _, code in BLOCKS if page.name == "README.md")
    for keyword in ("method=", "warmup=", "iterations=", "seed=", "out="):
        assert keyword in first, keyword


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A best_policy.json, as a finished run leaves it (the numpy-only recipe reads one)."""
    import ppprops

    out = tmp_path_factory.mktemp("policy") / "run"
    ppprops.search("CartPole", method="random", warmup=2, iterations=1, seed=0, out=out,
                   evaluation={"final_episodes": 1, "select_top": 0})
    return out / "best_policy.json"


@pytest.fixture(scope="module")
def folders(tmp_path_factory: pytest.TempPathFactory, policy_file: Path) -> dict[Path, Path]:
    """One folder per page, holding the example files and a policy file."""
    out = {}
    for page in PAGES:
        folder = tmp_path_factory.mktemp(page.stem)
        for f in (ROOT / "examples" / "own_robot").glob("*"):
            if f.is_file():
                shutil.copy(f, folder / f.name)
        shutil.copy(ROOT / "examples" / "robot_outside" / "robot.toml", folder / "robot.toml")
        shutil.copy(policy_file, folder / "best_policy.json")
        (folder / "harness.py").write_text(HARNESS)
        out[page] = folder
    return out


RUNNABLE = [(p, line, code) for p, line, code in BLOCKS if not is_fragment(code)]


@pytest.mark.parametrize(("page", "line", "code"), RUNNABLE, ids=[f"{p.name}:{line}" for p, line, _ in RUNNABLE])
def test_a_page_block_runs_as_written(page: Path, line: int, code: str, folders: dict[Path, Path]) -> None:
    folder = folders[page]
    script = folder / f"block_{line}.py"
    script.write_text(code)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(folder), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "harness.py", script.name], cwd=folder, capture_output=True, text=True, env=env,
                          timeout=600)
    assert proc.returncode == 0, f"{page.name}:{line} failed:\n{proc.stderr[-3000:]}"
