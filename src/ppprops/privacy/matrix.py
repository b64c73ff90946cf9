"""``ppprops privacy-report``: attack x scheme recovery errors and search results, on real runs.

For every run it reads the recorded request bodies only (the transcript), runs every attack,
and only then compares the estimates with the run's true secrets from its key file. An attack
that finds nothing falls back to the prior guess (c = 1, a_j = 1: the geometric means of both
schemes' secret distributions), so "no better than a prior guess" is read off the same table.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..client.codec import grid_scale
from ..errors import ConfigError
from ..rundir import open_run, policy_path
from ..tasks.base import Task
from . import simfit
from .attacks import ATTACKS, TARGET, run_attacks
from .audit import audit_run, run_grid_factor, search_config
from .exposure import EXPOSED_WITHIN, shown_candidate
from .requests import load_requests
from .simfit import SimLimits

SCHEMES = ("pp", "pp-hardened")
PRIOR = 1.0  # geometric mean of the priors of c and a_j, in both schemes


@dataclass
class RunAnalysis:
    """One run's privacy analysis: its search result and audit verdict, and per attack the recovery
    error of the secret it targets (error factor - 1: exp(abs(ln(estimate / true))) - 1).
    """

    run_dir: str
    task: str
    method: str
    seed: int
    warmup: int
    iterations: int
    best_return: float
    final_mean: float | None
    llm_calls: int
    fallbacks: int
    audit: str
    model: str = ""  # as named in the request bodies
    errors: dict[str, float] = field(default_factory=dict)  # attack -> relative error of the recovered secret
    applicable: dict[str, bool] = field(default_factory=dict)
    details: dict[str, str] = field(default_factory=dict)
    coverage: dict[str, float] = field(default_factory=dict)  # share of the D coordinates an a-attack estimated
    coord_errors: dict[str, list[float]] = field(default_factory=dict)  # a-attacks: one error per scored coordinate
    not_run: dict[str, str] = field(default_factory=dict)  # attack -> why it could not run on this run
    within: dict[str, bool] = field(default_factory=dict)  # attack -> recovered its secret within 1% on this run
    paced: bool = False  # the run paced its requests (pace_requests)
    timing: str = ""  # the audit on the provider's clock: "" (nothing found), "channel" or "exposed"
    anchored: bool = False  # a shown diagnostic pinned a shown raw return at a public cap (the audit's anchored_return)

    def to_json(self) -> dict[str, Any]:
        """The JSON form written to ``privacy-report.json``."""
        return dict(self.__dict__)


def _rel(est: float | np.ndarray, true: float | np.ndarray) -> Any:
    """Symmetric error factor minus one: exp(|ln(est/true)|) - 1 (0.01 = within 1%, 1.0 = off by 2x either way)."""
    return np.expm1(np.abs(np.log(np.asarray(est, dtype=np.float64) / true)))


RAW_ROW = "raw return (sim-exact)"  # the best shown policy's raw return as the exact simulator fit decodes it


def analyse_run(run_dir: Path, limits: SimLimits | None = None, *, simulate: bool = True) -> RunAnalysis:
    """Attacks on one run's transcript, scored against its key file; plus its search result.

    The attacks run once, inside the run's audit (simulator attacks within ``limits``); their
    estimates are scored here; ``simulate=False`` leaves the simulator attacks out. Raises
    StoreError / KeyFileError for an unreadable run or key file.
    """
    run_dir = Path(run_dir)
    with open_run(run_dir) as run:
        config = search_config(run.stored, run_dir)
        task = run.task
        secrets = run.load_secrets()
        cands = run.store.candidates()
        fe = run.store.final_eval()
        calls = run.store.llm_calls()
    m = config.mechanisms
    true_c = secrets.c if m.scale_rewards else 1.0
    true_a = run_grid_factor(config, secrets) * np.asarray(secrets.a) if m.encode_params else np.ones(task.D)  # g a_j on the grid
    # the prior guess of a_j: 1, times the geometric mean of the grid factor's public range [G/2, G] on the grid
    prior_a = PRIOR * (grid_scale(config.box, m.warp_params) / math.sqrt(2.0) if config.numbers == "grid" and m.encode_params else 1.0)
    out = RunAnalysis(
        run_dir=str(run_dir), task=task.name, method=config.method, seed=config.seed, warmup=config.warmup,
        iterations=config.iterations, best_return=max((c.ret for c in cands), default=math.nan),
        final_mean=fe.mean if fe is not None and fe.returns else None, llm_calls=len(calls),
        fallbacks=sum(c.source == "fallback" for c in cands), audit="",
    )
    report = audit_run(run_dir, limits=limits, simulate=simulate)
    out.audit = report.verdict()
    out.paced = m.pace_requests
    kinds = {(f.kind, f.severity) for f in report.findings}
    out.timing = "exposed" if ("request-timing", "exposed") in kinds else "channel" if ("request_timing", "channel") in kinds else ""
    out.anchored = any(k == "anchored_return" for k, _ in kinds)
    requests = load_requests(run_dir)
    out.model = _model_of(calls) if requests else ""
    estimates = report.estimates or run_attacks(requests, task, config.box, limits=limits, simulate=simulate)
    for est in estimates:
        if est.not_run:
            out.not_run[est.attack] = est.not_run
        if est.attack == "sim-exact" and est.raw and m.encode_params:
            best = max(est.raw, key=lambda g: g.ret)
            c = shown_candidate(best, cands)
            if c is not None and c.ret != 0 and math.isfinite(best.raw_ret):
                out.errors[RAW_ROW] = float(abs(best.raw_ret - c.ret) / abs(c.ret))
                out.applicable[RAW_ROW] = True
        if est.target == "c":
            value = float(est.value) if est.applicable and est.value is not None else PRIOR
            out.errors[est.attack] = float(_rel(value, true_c))
        else:
            arr = np.full(task.D, np.nan) if est.value is None else np.asarray(est.value, dtype=np.float64)
            known = np.isfinite(arr) & (arr > 0)
            # scored on the coordinates the attack estimated; with none, the attacker has only the prior
            coords = _rel(arr[known], true_a[known]) if known.any() else _rel(prior_a, true_a)
            out.coord_errors[est.attack] = [float(x) for x in np.atleast_1d(coords)]
            out.errors[est.attack] = float(np.median(coords))
            out.coverage[est.attack] = float(known.mean())
        out.applicable[est.attack] = est.applicable
        out.details[est.attack] = est.detail
        if est.applicable:
            scored = out.coord_errors[est.attack] if est.target == "a" else [out.errors[est.attack]]
            out.within[est.attack] = bool(np.median(scored) <= EXPOSED_WITHIN)
    if RAW_ROW in out.errors:
        out.within[RAW_ROW] = out.errors[RAW_ROW] <= EXPOSED_WITHIN
    out.errors["prior (c)"] = float(_rel(PRIOR, true_c))
    out.coord_errors["prior (a)"] = [float(x) for x in _rel(np.full(task.D, prior_a), true_a)]
    out.errors["prior (a)"] = float(np.median(out.coord_errors["prior (a)"]))
    return out


def _model_of(calls: Sequence[dict[str, Any]]) -> str:
    """The model named in the first recorded request body (the offline stand-in sends none)."""
    try:
        if calls[0]["response"] is None and calls[0]["ok"]:
            return "offline stand-in (EchoOptimizer)"  # it answers without an HTTP response body
        return str(json.loads(calls[0]["request"]).get("model", ""))
    except (ValueError, IndexError, AttributeError):
        return ""


def run_matrix(
    out: Path, *, envs: Sequence[str | Task], seeds: Sequence[int], schemes: Sequence[str] = SCHEMES, warmup: int = 10,
    iterations: int = 10, final_episodes: int = 20, log: Callable[[str], None] = print, offline: bool = False,
    settings: Mapping[str, Any] | None = None,
) -> list[Path]:
    """One run per (task, scheme, seed) with the embedded model (or the offline stand-in), in
    ``out/<task>__<scheme>__<seed>``; finished runs are kept, so a stopped matrix continues.

    ``envs``: task names, or Tasks (a user's task file, as ``load_task`` reads it); ``settings``:
    run settings over each scheme's preset, by their setting names (``{"pace_requests": True}``,
    ``{"number_format": "grid"}``). Returns the run
    directories. Raises ConfigError for an unfinished run in the way, UnknownTaskError for a name
    that names no task.
    """
    from ..runner import start
    from ..settings import build_config
    from ..tasks import get_task
    from .simulate import EchoOptimizer

    tasks = [env if isinstance(env, Task) else get_task(env) for env in envs]
    dirs = []
    for seed in seeds:
        for task in tasks:
            for scheme in schemes:
                d = Path(out) / f"{task.name}__{scheme}__{seed}"
                dirs.append(d)
                if policy_path(d).exists():
                    continue
                if d.exists():
                    raise ConfigError(f"{d} holds an unfinished run; finish it with 'ppprops resume {d}' or remove it")
                t0 = time.time()
                cfg = build_config({"method": scheme, "warmup": warmup, "iterations": iterations,
                                    "final_episodes": final_episodes, "seed": seed, **(settings or {})}, task=task)  # fmt: skip
                start(cfg, d, llm=EchoOptimizer(cfg.llm) if offline else None)
                log(f"{d}: done in {time.time() - t0:.0f} s")
    return dirs


def _fmt_err(values: list[float], within: list[bool], coverage: list[float] | None = None, not_run: int = 0,
             applicable: list[bool] | None = None) -> str:
    med = float(np.median(values)) if values else math.nan
    pct = "-" if not values else f"{100 * med:.2g}%" if med < 1e-3 else f"{100 * med:.3g}%" if med < 1 else f"{100 * med:.0f}%"
    cov = ""
    if coverage and applicable and any(applicable) and min(coverage) < 1.0:
        cov = f", {100 * float(np.mean([c for c, a in zip(coverage, applicable, strict=True) if a])):.0f}% of coords"
    nr = f", {not_run} not run" if not_run else ""
    return f"{pct} ({sum(within)}/{len(within)}{cov}{nr})"


def format_report(runs: Sequence[RunAnalysis], limits: SimLimits | None = None) -> str:
    """The report as Markdown: one row per attack (and the prior guesses), one column per (task, scheme); then the search results."""
    groups: dict[tuple[str, str], list[RunAnalysis]] = {}
    for r in runs:
        groups.setdefault((r.task, r.method + (", paced" if r.paced else "")), []).append(r)
    cols = sorted(groups, key=lambda k: (k[0], SCHEMES.index(k[1].split(",")[0]) if k[1].split(",")[0] in SCHEMES else 9, k[1]))
    head = "| attack | secret | " + " | ".join(f"{t} {m}" for t, m in cols) + " |"
    lim = limits or simfit.DEFAULT_LIMITS
    lines = [
        "Recovery error of the secret: error factor - 1, i.e. exp(|ln(estimate / true)|) - 1 (1% = within 1%, 100% = off by 2x",
        "either way). For c: the median over runs. For a: the median over every coordinate the attack estimated, all runs pooled.",
        "(k/n): runs in which the attack recovered the secret within 1% (for a: the median over the coordinates it estimated);",
        "an attack that found nothing counts as the prior guess 1 (the geometric mean of the secret's distribution in both",
        "schemes), also in the median; 'not run': runs where it could not run (the reason is in privacy-report.json).",
        "'prior' rows: that guess alone. 'raw return (sim-exact)': relative error of the best shown policy's raw return as the",
        f"exact simulator fit decodes it. Simulator attacks are bounded by {lim.describe()}.",
        "",
        head,
        "|" + "---|" * (len(cols) + 2),
    ]
    rows = [(name, TARGET[name]) for name in ATTACKS]
    rows += [(RAW_ROW, "r"), ("prior (c)", "c"), ("prior (a)", "a")]
    for name, target in rows:
        cells = []
        for key in cols:
            rs = groups[key]
            # c: one value per run; a: every scored coordinate of every run, pooled (D times more draws)
            scored = [r for r in rs if name in r.errors]
            if name in rs[0].coord_errors:
                errs = [x for r in scored for x in r.coord_errors.get(name, [])]
            else:
                errs = [r.errors[name] for r in scored]
            prior_row = name.startswith("prior")
            within = [r.within.get(name, False) if not prior_row else bool(r.errors[name] <= EXPOSED_WITHIN) for r in rs]
            nr = sum(name in r.not_run for r in rs)
            cov = [r.coverage[name] for r in rs] if name in rs[0].coverage else None
            apps = [r.applicable.get(name, False) for r in rs]
            cells.append(_fmt_err(errs, within, cov, nr, apps))
        lines.append(f"| {name} | {target} | " + " | ".join(cells) + " |")
    models = ", ".join(sorted({r.model for r in runs if r.model})) or "-"
    lines += ["", f"Search results (best return found during the search; final evaluation of that policy on fresh episodes); "
              f"model: {models}:", "",
              "| task | scheme | runs | warm-up + iterations | best search return | final evaluation | fallbacks | audit clean | audit exposed "
              "| provider's clock: channel / exposed | anchored return |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for key in cols:
        rs = groups[key]
        best = np.array([r.best_return for r in rs])
        finals = np.array([r.final_mean for r in rs if r.final_mean is not None])
        final = f"{finals.mean():.1f} +- {finals.std():.1f}" if len(finals) else "-"
        budget = ", ".join(sorted({f"{r.warmup} + {r.iterations}" for r in rs}))
        clean = sum(r.audit.startswith("CLEAN") for r in rs)
        exposed = sum(r.audit.startswith("EXPOSED") for r in rs)
        lines.append(f"| {key[0]} | {key[1]} | {len(rs)} | {budget} | {best.mean():.1f} +- {best.std():.1f} | {final} | "
                     f"{sum(r.fallbacks for r in rs)} | {clean}/{len(rs)} | {exposed}/{len(rs)} | "
                     f"{sum(r.timing == 'channel' for r in rs)}/{len(rs)} / {sum(r.timing == 'exposed' for r in rs)}/{len(rs)} | "
                     f"{sum(r.anchored for r in rs)}/{len(rs)} |")
    lines += ["", "Provider's clock: runs whose request gaps follow the episodes significantly (a channel), or give the best shown "
              "raw return within 1% (exposed); anchored return: runs where a shown diagnostic pins a shown raw return at a public cap. "
              "`ppprops audit RUN` gives each run's figures."]
    return "\n".join(lines)


def privacy_report(run_dirs: Sequence[Path], limits: SimLimits | None = None,
                   log: Callable[[str], None] | None = None, *, simulate: bool = True) -> tuple[str, list[RunAnalysis]]:
    """Analyse every run in ``run_dirs`` (``analyse_run``, simulator attacks within ``limits``, or
    none with ``simulate=False``) and format the report: (Markdown text, analyses). ``log`` hears
    one line per run analysed.

    Raises StoreError / KeyFileError for a directory that is not a run or has no usable key file.
    """
    analyses = []
    for d in run_dirs:
        t0 = time.time()
        analyses.append(analyse_run(d, limits, simulate=simulate))
        if log is not None:
            log(f"{d}: analysed in {time.time() - t0:.0f} s")
    return format_report(analyses, limits), analyses


def write_report(out: Path, text: str, analyses: Sequence[RunAnalysis], command: str) -> None:
    """Write ``privacy-report.md`` (with the producing ``command``) and ``privacy-report.json`` into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "privacy-report.md").write_text(f"# Privacy report\n\nProduced by: `{command}`\n\n{text}\n", encoding="utf-8")
    (out / "privacy-report.json").write_text(json.dumps([a.to_json() for a in analyses], indent=1), encoding="utf-8")
