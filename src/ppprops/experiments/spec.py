"""Experiment specs: which runs a grid holds, and the exact settings of each.

A spec (TOML, or YAML with the ``experiments`` extra) names tasks x methods x seeds in groups,
with run settings keyed like the flags of ``ppprops run`` (``top-k = 0``, ``base-url = ...``), so a
grid run is configured exactly as the same ``ppprops run`` command would be: settings are read and
checked by ``ppprops.settings`` (the one schema of run settings) and become a RunConfig through
``settings.build_config``, as flags do. RL
baselines (``ppprops baseline rl``) form groups of their own; combinations the paper marks "--"
(SAC/TD3/DDPG on discrete actions, DQN on continuous ones) are skipped and listed.

Layout (every key but ``grid``/``rl`` optional)::

    name = "main_results"
    seeds = 5                          # 5 -> seeds 0..4, or a list [0, 3, 7]
    [run]                              # settings of every search run, as `ppprops run` flags
    warmup = 10
    top-k = 10
    [execution]                        # jobs, llm-threads, llm-concurrency (flags win)
    [[grid]]                           # a group of search runs
    tasks = ["CartPole", "Acrobot"]
    methods = ["vanilla", "pp"]
    label = "K0"                       # optional: names a variant, e.g. with run = { top-k = 0 }
    run = { top-k = 0 }                # optional: this group's settings over [run]
    [[rl]]                             # a group of RL baseline runs
    tasks = ["CartPole"]
    algos = ["ppo", "dqn"]
    timesteps = 100000
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..config import RunConfig, read_table
from ..errors import ConfigError
from ..methods import search_method_names
from ..settings import build_config, read_settings
from ..status import RunKind

# Settings a grid sets itself, per run; they are no `ppprops experiment` flag and no [run] key.
RESERVED = frozenset({"env", "method", "seed"})
_SET_BY_GRID = "is set by the grid (tasks, methods, seeds, --out), not as a run setting"
RESERVED_KEYS = {k: _SET_BY_GRID for k in ("env", "method", "seed", "out", "config", "quiet")}
TOP_KEYS = ("name", "description", "seeds", "run", "execution", "grid", "rl")
GROUP_KEYS = ("tasks", "methods", "label", "seeds", "run")
RL_KEYS = ("tasks", "algos", "timesteps", "seeds", "final-episodes", "device", "threads")
EXECUTION_KEYS = ("jobs", "llm-threads", "llm-concurrency")
_LABEL = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+]*$")
SEARCH = RunKind.SEARCH  # kept as names: grid.json and callers use them
RL = RunKind.RL


@dataclass(frozen=True)
class PlannedRun:
    """One run of a grid: its directory name and the full configuration it is started with."""

    name: str
    kind: RunKind  # a search (ppprops run) or an RL baseline (ppprops baseline rl)
    task: str
    method: str  # a `ppprops run` method, or rl-<algo>
    label: str  # variant label of its group ("" when none)
    seed: int
    config: dict[str, Any]  # RunConfig.to_json() or the RLConfig fields

    @property
    def arm(self) -> str:
        """The method with its group label (``pp-K0``), or the method alone: the middle of the run name."""
        return f"{self.method}-{self.label}" if self.label else self.method


@dataclass(frozen=True)
class Execution:
    """How a grid runs; none of it changes a result (llm_threads must match to repeat one exactly)."""

    jobs: int | None = None  # runs at once; None: cores // llm_threads
    llm_threads: int = 1  # threads of each run's embedded llama.cpp server (and of nothing else)
    llm_concurrency: int | None = None  # cap on LLM requests in flight across the grid; None: 4 for a remote endpoint

    def validate(self) -> None:
        """Check the ranges (flag names in the messages).

        Raises:
            ConfigError: ``jobs``, ``llm_threads`` or ``llm_concurrency`` outside [1, 1024].
        """
        if self.jobs is not None and not (1 <= self.jobs <= 1024):
            raise ConfigError(f"--jobs must be in [1, 1024], got {self.jobs}")
        if not (1 <= self.llm_threads <= 1024):
            raise ConfigError(f"--llm-threads must be in [1, 1024], got {self.llm_threads}")
        if self.llm_concurrency is not None and not (1 <= self.llm_concurrency <= 1024):
            raise ConfigError(f"--llm-concurrency must be in [1, 1024], got {self.llm_concurrency}")


@dataclass(frozen=True)
class ExperimentSpec:
    """A spec expanded into its runs: name and description from the file, the runs in execution
    order (seed-major), how to execute them, and the RL combinations skipped as the paper's "--".

    ``source`` is the spec file's path, or "flags" for the ``--tasks``/``--methods`` form.
    """

    name: str
    description: str
    runs: tuple[PlannedRun, ...]
    execution: Execution = field(default_factory=Execution)
    skipped: tuple[str, ...] = ()  # "task rl-algo" combinations left out as inapplicable
    source: str = "flags"


# -- reading ---------------------------------------------------------------------------------
def read_spec_file(path: Path) -> dict[str, Any]:
    """A spec file as a table: TOML by default, YAML for .yaml/.yml (the ``experiments`` extra)."""
    return read_table(Path(path), "spec file")


def flags_table(tasks: Sequence[str], methods: Sequence[str], seeds: int | list[int]) -> dict[str, Any]:
    """The spec of the flag form (``--tasks A,B --methods m,n --seeds 2``)."""
    return {"name": "grid", "seeds": seeds, "grid": [{"tasks": list(tasks), "methods": list(methods)}]}


def parse_seeds(value: Any, where: str) -> list[int]:
    """``5`` means seeds 0..4; a list names them."""
    if isinstance(value, bool):
        raise ConfigError(f"{where}: seeds must be a count or a list of integers, got {value!r}")
    if isinstance(value, int):
        if not (1 <= value <= 10_000):
            raise ConfigError(f"{where}: seeds must be in [1, 10000], got {value}")
        return list(range(value))
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        if any(v < 0 for v in value) or len(set(value)) != len(value):
            raise ConfigError(f"{where}: seeds must be distinct non-negative integers, got {value!r}")
        return list(value)
    raise ConfigError(f"{where}: seeds must be a count or a non-empty list of integers, got {value!r}")


def seeds_flag(text: str) -> int | list[int]:
    """argparse type of ``--seeds``: ``5`` or ``0,3,7``."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a count or a comma list of seeds, got {text!r}") from None
    return values[0] if len(values) == 1 and "," not in text else values


def _check_keys(table: Mapping[str, Any], allowed: Iterable[str], where: str) -> None:
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where} must be a table, got {table!r}")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} (known: {', '.join(allowed)})")


def _names(value: Any, where: str) -> list[str]:
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    if not (isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)):
        raise ConfigError(f"{where} must be a non-empty list of names, got {value!r}")
    if len(set(value)) != len(value):
        raise ConfigError(f"{where} names something twice: {value!r}")
    return list(value)


def _int(table: Mapping[str, Any], key: str, where: str, default: int | None = None) -> int | None:
    value = table.get(key, default)
    if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
        raise ConfigError(f"{where}: {key} must be an integer, got {value!r}")
    return value


# -- run settings -------------------------------------------------------------------------------
def run_settings(table: Mapping[str, Any], where: str) -> dict[str, Any]:
    """A spec's run settings (``[run]``, a group's ``run``), checked like a ``ppprops run --config`` file."""
    return read_settings(table, where, unknown="unknown run setting", reserved=RESERVED_KEYS)


def run_config(task: str, method: str, seed: int, settings: Mapping[str, Any]) -> RunConfig:
    """The RunConfig that ``ppprops run --env task --method method --seed seed <settings>`` builds."""
    methods = search_method_names()
    if method not in methods:
        raise ConfigError(f"unknown method {method!r}; choose from {', '.join(methods)} (RL baselines go in [[rl]] groups)")
    return build_config({**settings, "env": task, "method": method, "seed": seed})


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", text)


def run_name(task: str, arm: str, seed: int) -> str:
    """``<task>__<method[-label]>__<seed>``: the run's directory name and its run id."""
    return f"{_safe(task)}__{arm}__{seed}"


def build_spec(
    raw: Mapping[str, Any],
    *,
    source: str = "flags",
    overrides: Mapping[str, Any] | None = None,
    seeds: int | list[int] | None = None,
    only_tasks: Sequence[str] | None = None,
    only_methods: Sequence[str] | None = None,
    execution: Mapping[str, Any] | None = None,
) -> ExperimentSpec:
    """Expand a spec table into its runs. ``overrides`` (parsed `run` flags), ``seeds`` and
    ``execution`` win over the file; ``only_tasks``/``only_methods`` keep a subset of its runs.

    Raises:
        ConfigError: an unknown key, a bad setting or seed list, no runs (or none left by the
            selection), an unknown method or RL algorithm, an RL group without ``timesteps``, two
            groups making the same run.
        UnknownTaskError: a task that names no task.
    """
    where = source
    _check_keys(raw, TOP_KEYS, where)
    if not raw.get("grid") and not raw.get("rl"):
        raise ConfigError(f"{where}: no runs: add [[grid]] groups (tasks, methods) or [[rl]] groups")
    base = run_settings(raw.get("run", {}), f"{where} [run]")
    base.update(overrides or {})
    top_seeds = parse_seeds(seeds if seeds is not None else raw.get("seeds", 5), where)
    exe_table = dict(raw.get("execution", {}))
    _check_keys(exe_table, EXECUTION_KEYS, f"{where} [execution]")
    exe_values = {"jobs": _int(exe_table, "jobs", where), "llm_threads": _int(exe_table, "llm-threads", where, 1),
                  "llm_concurrency": _int(exe_table, "llm-concurrency", where)}  # fmt: skip
    exe_values.update({k: v for k, v in (execution or {}).items() if v is not None})
    exe = Execution(**exe_values)  # type: ignore[arg-type]
    exe.validate()

    from ..tasks import get_task

    # (seed, group, task, method): seed-major, so a partial grid already holds whole tables of the first seeds
    planned: list[tuple[int, int, PlannedRun]] = []
    skipped: list[str] = []
    for gi, group in enumerate(raw.get("grid", []) or []):
        gw = f"{where} [[grid]] #{gi + 1}"
        _check_keys(group, GROUP_KEYS, gw)
        tasks = [get_task(t).name for t in _names(group.get("tasks"), f"{gw} tasks")]
        methods = _names(group.get("methods"), f"{gw} methods")
        label = str(group.get("label", ""))
        if label and not _LABEL.match(label):
            raise ConfigError(f"{gw}: label must be letters, digits and _ . + (starting with a letter or digit), got {label!r}")
        settings = {**base, **run_settings(group.get("run", {}), f"{gw} run")}
        settings.update(overrides or {})
        group_seeds = top_seeds if seeds is not None or "seeds" not in group else parse_seeds(group["seeds"], gw)
        for seed in group_seeds:
            for task in tasks:
                for method in methods:
                    config = run_config(task, method, seed, settings)
                    arm = f"{method}-{label}" if label else method
                    run = PlannedRun(run_name(task, arm, seed), SEARCH, task, method, label, seed, config.to_json())
                    planned.append((seed, gi, run))
    rl_groups = raw.get("rl", []) or []
    for ri, group in enumerate(rl_groups):
        rw = f"{where} [[rl]] #{ri + 1}"
        _check_keys(group, RL_KEYS, rw)
        from ..baselines.rl import RLConfig
        from ..methods import rl_method

        tasks = [get_task(t).name for t in _names(group.get("tasks"), f"{rw} tasks")]
        algos = _names(group.get("algos"), f"{rw} algos")
        for algo in algos:
            try:
                rl_method(algo)
            except ConfigError as e:
                raise ConfigError(f"{rw}: {e}") from None
        timesteps = _int(group, "timesteps", rw)
        if timesteps is None:
            raise ConfigError(f"{rw}: timesteps is required (the paper does not state its RL budgets)")
        final = _int(group, "final-episodes", rw, base.get("final_episodes", 20))
        threads = _int(group, "threads", rw, 1)
        device = str(group.get("device", "cpu"))
        group_seeds = top_seeds if seeds is not None or "seeds" not in group else parse_seeds(group["seeds"], rw)
        for seed in group_seeds:
            for task in tasks:
                for algo in algos:
                    if not rl_method(algo).algorithm.applies_to(get_task(task).action_type):
                        if seed == group_seeds[0]:
                            skipped.append(f"{task} rl-{algo}")
                        continue
                    rl = RLConfig(task=task, algo=algo, timesteps=int(timesteps), seed=seed, final_episodes=int(final or 0),
                                  device=device, threads=int(threads or 1))  # fmt: skip
                    rl.validate()
                    run = PlannedRun(run_name(task, rl.method, seed), RL, task, rl.method, "", seed, asdict(rl))
                    planned.append((seed, len(raw.get("grid", []) or []) + ri, run))
    planned.sort(key=lambda t: (t[0], t[1]))  # stable: task, method order kept inside a group
    runs = [p[2] for p in planned]
    if only_tasks:
        want = {get_task(t).name for t in only_tasks}
        runs = [r for r in runs if r.task in want]
    if only_methods:
        runs = [r for r in runs if r.method in only_methods or r.arm in only_methods]
    if not runs:
        raise ConfigError(f"{where}: the selection leaves no runs")
    seen: dict[str, PlannedRun] = {}
    for r in runs:
        if r.name in seen:
            raise ConfigError(f"{where}: two groups make run {r.name}; give one of them a label")
        seen[r.name] = r
    name = str(raw.get("name", "grid"))
    return ExperimentSpec(name=name, description=str(raw.get("description", "")), runs=tuple(runs), execution=exe,
                          skipped=tuple(skipped), source=source)  # fmt: skip


def load_spec(path: Path, **kw: Any) -> ExperimentSpec:
    """Read the spec file ``path`` (TOML, or YAML) and expand it: ``build_spec`` with the file's path as source.

    Raises:
        ConfigError: the file is missing or unreadable, or its content is wrong (see ``build_spec``).
        MissingExtraError: a YAML file without the ``experiments`` extra.
    """
    return build_spec(read_spec_file(path), source=str(path), **kw)
