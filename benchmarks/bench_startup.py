"""9. Command start-up: the CPU time of `ppprops --help`, `ppprops ask` and `ppprops tell`.

    python benchmarks/bench_startup.py [--n 10]           # prints the table
    python benchmarks/run_all.py --only startup           # the same, as section 9 of RESULTS.md

A robot driven from the shell starts `ppprops ask` and `ppprops tell` once per trial each, so their
start-up is paid twice per trial. The benchmark creates a study (CartPole, random search, 2 warm-up
+ 2 iterations), asks once (the trial is stored), then runs each command ``--n`` times, round by
round (so load changes hit all alike), and reports the median CPU time (user + sys of the child:
``getrusage(RUSAGE_CHILDREN)`` deltas) beside `python -c pass` and `python -c "import numpy"`:

- `ppprops ask DIR` asks for the stored trial again (no LLM, no proposer);
- `ppprops tell DIR 0 --return 1` tells it, each time on a fresh copy of the study (copied by this
  process, outside the measurement), so every tell succeeds;
- for comparison: numpy's import with OpenBLAS's worker threads sleeping at once
  (``OPENBLAS_THREAD_TIMEOUT=4``, as ask and tell load it), and ask and tell with OpenBLAS's
  default spin set explicitly (``OPENBLAS_THREAD_TIMEOUT=28``, which they then keep).

Python finds ppprops' bytecode one of two ways, and both are measured, each on its own copy of the
ppprops package measured (the one this process imports; ``PYTHONPATH=/other/src`` measures another
checkout) in a temporary directory: compiled from source at every start (``PYTHONDONTWRITEBYTECODE=1``
and no ``__pycache__``, as the development environment of this project runs it), and cached (the
``.pyc`` files written by a first start, as an installed package has them). The target, at most
0.35 s of CPU per command, holds when it holds both ways.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

TARGET_S = 0.35  # CPU seconds per command (user + sys)
COMMANDS = ("pass", "numpy", "numpy-idle", "help", "ask", "tell", "ask-spin", "tell-spin")
LABELS = {"pass": "`python -c pass`", "numpy": '`python -c "import numpy"`',
          "numpy-idle": '`OPENBLAS_THREAD_TIMEOUT=4 python -c "import numpy"`', "help": "`ppprops --help`",
          "ask": "`ppprops ask DIR` (stored trial)", "tell": "`ppprops tell DIR 0 --return 1`",
          "ask-spin": "`OPENBLAS_THREAD_TIMEOUT=28 ppprops ask DIR`", "tell-spin": "`OPENBLAS_THREAD_TIMEOUT=28 ppprops tell DIR 0 --return 1`"}
TARGETED = ("help", "ask", "tell")
# OpenBLAS's worker threads spin 2^OPENBLAS_THREAD_TIMEOUT cycles once started (default 28: about 0.1 s
# of another core); ppprops ask and tell load numpy with 4 unless it is set. The *-spin rows set
# OpenBLAS's default explicitly, which they keep: what the commands cost without that.
BLAS_TIMEOUT = {"numpy-idle": "4", "ask-spin": "28", "tell-spin": "28"}
MODES = (("compiled", "compiled at each start"), ("cached", "bytecode cached"))


def _package_dir() -> Path:
    """The directory holding the ppprops package this process imports (what PYTHONPATH names)."""
    import ppprops

    return Path(ppprops.__file__).resolve().parent.parent


def _env(src: Path, mode: str, command: str = "") -> dict[str, str]:
    drop = ("PYTHONDONTWRITEBYTECODE", "PYTHONPYCACHEPREFIX", "OPENBLAS_THREAD_TIMEOUT")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PYTHONPATH"] = str(src)
    if mode == "compiled":
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    if command in BLAS_TIMEOUT:
        env["OPENBLAS_THREAD_TIMEOUT"] = BLAS_TIMEOUT[command]
    return env


def _cpu(argv: Sequence[str], env: dict[str, str], cwd: Path) -> tuple[float, str]:
    """(user + sys seconds of the child, its stdout); the command must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(list(argv), env=env, cwd=cwd, capture_output=True, text=True, timeout=600)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {proc.returncode}: {proc.stderr.strip()}")
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), proc.stdout


def measure(n: int = 10, work: Path | None = None) -> dict[str, Any]:
    """Median, min and max CPU seconds of each command in each mode, over ``n`` interleaved rounds."""
    py = sys.executable
    src = _package_dir()
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        root = Path(tmp) if work is None else work
        copies = {}
        for mode, _ in MODES:  # a package copy per mode: no __pycache__ in one, its own in the other
            copies[mode] = root / f"src-{mode}"
            shutil.rmtree(copies[mode], ignore_errors=True)
            shutil.copytree(src / "ppprops", copies[mode] / "ppprops", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        study = root / "study"
        shutil.rmtree(study, ignore_errors=True)
        env0 = _env(copies["compiled"], "compiled")
        _cpu([py, "-m", "ppprops", "study", "create", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "2",
              "--out", str(study)], env0, root)  # fmt: skip
        _, asked = _cpu([py, "-m", "ppprops", "ask", str(study)], env0, root)  # the trial is stored now
        told = root / "told"

        def argv(command: str) -> list[str]:
            command = command.removesuffix("-spin").removesuffix("-idle")
            if command == "tell":  # a fresh copy of the study with its trial pending, so the tell succeeds
                shutil.rmtree(told, ignore_errors=True)
                shutil.copytree(study, told)
            return {"pass": [py, "-c", "pass"], "numpy": [py, "-c", "import numpy"], "help": [py, "-m", "ppprops", "--help"],
                    "ask": [py, "-m", "ppprops", "ask", str(study)],
                    "tell": [py, "-m", "ppprops", "tell", str(told), "0", "--return", "1"]}[command]  # fmt: skip

        for command in COMMANDS:  # the cached mode's first start writes its bytecode
            _cpu(argv(command), _env(copies["cached"], "cached", command), root)
        times: dict[str, dict[str, list[float]]] = {mode: {c: [] for c in COMMANDS} for mode, _ in MODES}
        load = [os.getloadavg()[0]]
        for _ in range(n):
            for mode, _ in MODES:
                for command in COMMANDS:
                    seconds, out = _cpu(argv(command), _env(copies[mode], mode, command), root)
                    if command.startswith("ask") and out != asked:
                        raise AssertionError("ppprops ask printed another trial than the stored one")
                    if command.startswith("tell") and not out.startswith("trial 0: return 1"):
                        raise AssertionError(f"ppprops tell printed {out!r}")
                    times[mode][command].append(seconds)
        load.append(os.getloadavg()[0])
    stats = {mode: {c: {"median": statistics.median(v), "min": min(v), "max": max(v), "runs": v} for c, v in per.items()}
             for mode, per in times.items()}  # fmt: skip
    return {"n": n, "python": py, "ppprops": str(src), "load": load, "target_s": TARGET_S, "modes": stats}


def met(data: dict[str, Any], command: str) -> bool:
    return all(data["modes"][mode][command]["median"] <= TARGET_S for mode, _ in MODES)


def rows(data: dict[str, Any]) -> list[list[str]]:
    out = []
    for c in COMMANDS:
        cells = [LABELS[c]]
        for mode, _ in MODES:
            s = data["modes"][mode][c]
            cells.append(f"{s['median']:.3f} ({s['min']:.2f}-{s['max']:.2f})")
        cells += [f"<= {TARGET_S:.2f}", "met" if met(data, c) else "**not met**"] if c in TARGETED else ["(for comparison)", ""]
        out.append(cells)
    return out


HEADER = ["command", "CPU s, compiled at each start: median (min-max)", "CPU s, bytecode cached: median (min-max)", "target", ""]


def run(ctx):  # type: ignore[no-untyped-def]  # the suite's entry point (run_all.py)
    from _common import Section, table

    n = 3 if ctx.quick else 10
    data = measure(n, ctx.dir("startup"))
    body = [f"CPU time (user + sys) of each command, median of {n} interleaved runs, ppprops from `{data['ppprops']}` "
            f"(load average {data['load'][0]:.2f} before, {data['load'][1]:.2f} after):", "",
            table(HEADER, rows(data)), "",
            "- A robot driven from the shell pays `ask` and `tell` once per trial each. The target (at most "
            f"{TARGET_S:g} s) holds when it holds both ways.",
            "- `ppprops ask` reads the stored trial from the store and checks the key file (no settings schema, task, codec "
            "or LLM client); `ppprops tell` loads the study (settings schema and pydantic, task, codec) to check and encode "
            "the feedback; `ppprops --help` builds no subcommand's arguments.",
            "- Once OpenBLAS (numpy's) starts, each of its worker threads spins for 2^OPENBLAS_THREAD_TIMEOUT cycles (default "
            "28, about 0.1 s of another core) before it sleeps; ask and tell load numpy with 4 unless the variable is set. "
            "The rows that set 28 show what they cost with OpenBLAS's default, the one above `ppprops --help` what numpy "
            "costs without the spin."]
    targets = []
    for c in TARGETED:
        m = data["modes"]
        targets.append((f"{LABELS[c]} <= {TARGET_S:g} s CPU (median, compiled at each start / bytecode cached)",
                        f"{m['compiled'][c]['median']:.3f} / {m['cached'][c]['median']:.3f} s (import numpy: "
                        f"{m['compiled']['numpy']['median']:.3f} / {m['cached']['numpy']['median']:.3f} s)", met(data, c)))
    return Section("startup", "9. Command start-up", "\n".join(body), data, targets=targets)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=10, help="runs of each command (interleaved); the median is reported")
    a = p.parse_args()
    data = measure(a.n)
    print(f"ppprops from {data['ppprops']}, {a.n} runs each, load {data['load'][0]:.2f} -> {data['load'][1]:.2f}")
    widths = [58, 24, 24, 18, 11]
    print("".join(h.ljust(w) for h, w in zip(["command", "compiled each start", "bytecode cached", "target", ""], widths, strict=True)))
    for r in rows(data):
        print("".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)))


if __name__ == "__main__":
    main()
