"""``ppprops report DIR``: the paper's tables and figures from a grid's runs, into ``DIR/report/``.

Every run is read through ``ppprops.summary.run_summary`` (the ``show --json`` object). Runs are
grouped by (task, method, top-K): K = 10 is the paper's default and needs no mark; other K are
their own column ("vanilla (unbounded)" for K = 0). Over the seeds of a group we report the mean
and the population standard deviation (numpy's default) of

- the search-time best return (the best candidate's return during the search; the paper's
  number), and
- the final-evaluation return (that policy on fresh episode seeds, never seen in the search).

RL baselines have no search: their score is the final evaluation, as in the paper's baselines
table. Runs that are not finished (or stopped on purpose) are listed but left out of the numbers.

Written: ``main_results``, ``bounded_history``, ``history_cost`` and ``baselines`` tables (each as
.md, .tex and .csv, when the grid holds runs for them), ``runs.csv``, ``summary.json``, one reward
curve and one history-cost figure per task (PNG), and ``index.html`` showing all of it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, MissingExtraError, StoreError
from ..methods import MethodKind, find_method
from ..status import RunKind
from . import paper_values as pv
from .order import DEFAULT_K, PROMPT_METHODS, column_key, task_key
from .records import Group, RunRecord, column_name, group_runs, read_run
from .tables import Cell, Table, write_csv, write_table


def _ms(mean: float | None, std: float | None) -> str:
    if mean is None:
        return ""
    return f"{mean:.2f} ({std:.2f})" if std is not None else f"{mean:.2f}"


def _paper_text(st: dict[str, Any]) -> str:
    if st["paper_table"] is None:
        return ""
    return pv.PaperValue(st["paper_mean"], st["paper_std"], st["paper_table"], st["paper_note"] or "").text()


def _n_mark(n: int, n_max: int) -> str:
    return f" [n={n}]" if n != n_max else ""


# -- tables ----------------------------------------------------------------------------------
STAT_COLUMNS = ["task", "column", "method", "top_k", "kind", "n", "seeds", "score_mean", "score_std", "best_mean", "best_std",
                "final_mean", "final_std", "paper_mean", "paper_std", "paper_table", "paper_note", "bold"]  # fmt: skip


def main_table(groups: dict[tuple[str, str], Group]) -> tuple[Table, list[dict[str, Any]]] | None:
    """Rows: tasks; per method: search-time best (best per row in bold), final evaluation, paper."""
    sel = {k: g for k, g in groups.items() if g.method_kind is MethodKind.PROMPTED}
    if not sel:
        return None
    tasks = sorted({t for t, _ in sel}, key=task_key)
    cols = sorted({c for _, c in sel}, key=column_key)
    stats = {k: g.stats() for k, g in sel.items()}
    n_max = max(s["n"] for s in stats.values())
    has_final = {c: any(stats[k]["final_mean"] is not None for k in stats if k[1] == c) for c in cols}
    has_paper = {c: any(stats[k]["paper_table"] is not None for k in stats if k[1] == c) for c in cols}
    header = ["Environment"]
    for c in cols:
        header.append(c)
        header += [f"{c} final"] if has_final[c] else []
        header += [f"{c} paper"] if has_paper[c] else []
    rows, csv_rows = [], []
    for t in tasks:
        present = [stats[(t, c)] for c in cols if (t, c) in stats and stats[(t, c)]["score_mean"] is not None]
        top = max((s["score_mean"] for s in present), default=None)
        row = [Cell(t)]
        for c in cols:
            st = stats.get((t, c))
            if st is None:
                row += [Cell("")] * (1 + has_final[c] + has_paper[c])
                continue
            bold = top is not None and st["score_mean"] == top
            row.append(Cell(_ms(st["best_mean"], st["best_std"]) + _n_mark(st["n"], n_max), bold))
            row += [Cell(_ms(st["final_mean"], st["final_std"]))] if has_final[c] else []
            row += [Cell(_paper_text(st))] if has_paper[c] else []
            csv_rows.append({**st, "seeds": " ".join(map(str, st["seeds"])), "bold": int(bold)})
        rows.append(row)
    notes = [f"Mean (std) over seeds of the search-time best return; 'final': the same policies on fresh episode seeds. "
             f"Best per row in bold. [n=k]: fewer seeds than the other cells ({n_max}).",
             "'paper': Table tab:all_results (unbounded vanilla: tab:bounded_history_performance), gpt-oss-20b; "
             "† see the paper's footnote."]  # fmt: skip
    return Table("main_results", "Episodic return of the best policy per method and task", header, rows, notes), csv_rows


def bounded_table(groups: dict[tuple[str, str], Group]) -> tuple[Table, list[dict[str, Any]]] | None:
    """K = 10 against unbounded (K = 0), for every task and method that has both."""
    pairs = []
    for (t, _), g in groups.items():
        if g.method_kind is MethodKind.PROMPTED and g.top_k == DEFAULT_K:
            unb = groups.get((t, column_name(g.method, 0, RunKind.SEARCH)))
            if unb is not None:
                pairs.append((g, unb))
    if not pairs:
        return None
    pairs.sort(key=lambda p: (task_key(p[0].task), column_key(p[0].column)))
    header = ["Environment", "D", "method", "Bounded (K=10)", "Unbounded", "Diff (%)", "paper K=10", "paper unbounded", "paper Diff (%)"]
    rows, csv_rows = [], []
    for k10, unb in pairs:
        a, b = k10.stats(), unb.stats()
        diff = None
        if a["best_mean"] is not None and b["best_mean"] not in (None, 0.0):
            diff = (a["best_mean"] - b["best_mean"]) / abs(b["best_mean"]) * 100.0
        ref = pv.bounded_value(k10.task) if k10.method == "vanilla" else None
        D = k10.runs[0].D
        better_k10 = a["best_mean"] is not None and b["best_mean"] is not None and a["best_mean"] >= b["best_mean"]
        rows.append([Cell(k10.task), Cell("" if D is None else str(D)), Cell(k10.method),
                     Cell(_ms(a["best_mean"], a["best_std"]), better_k10), Cell(_ms(b["best_mean"], b["best_std"]), not better_k10),
                     Cell("" if diff is None else f"{diff:+.2f}"),
                     Cell(ref[1].text() if ref else ""), Cell(ref[2].text() if ref else ""), Cell(f"{ref[3]:+.2f}" if ref else "")])  # fmt: skip
        csv_rows.append({"task": k10.task, "D": D, "method": k10.method, "n_k10": a["n"], "n_unbounded": b["n"],
                         "k10_mean": a["best_mean"], "k10_std": a["best_std"], "unbounded_mean": b["best_mean"],
                         "unbounded_std": b["best_std"], "diff_pct": diff, "k10_final_mean": a["final_mean"],
                         "unbounded_final_mean": b["final_mean"],
                         "paper_k10_mean": ref[1].mean if ref else None, "paper_unbounded_mean": ref[2].mean if ref else None,
                         "paper_diff_pct": ref[3] if ref else None})  # fmt: skip
    notes = ["Diff (%) = (K=10 - unbounded) / |unbounded| x 100 on the mean search-time best; the higher of the two in bold.",
             "paper: Table tab:bounded_history_performance (Vanilla ProPS on Ant)."]  # fmt: skip
    return Table("bounded_history", "Bounded (K=10) against unbounded history", header, rows, notes), csv_rows


def retained_history(run: RunRecord, iteration: int) -> int:
    """Entries in the prompt of LLM iteration ``iteration``: every candidate so far, or the top K."""
    seen = run.warmup + iteration
    return seen if not run.top_k else min(run.top_k, seen)


def history_cost_rows(groups: dict[tuple[str, str], Group]) -> list[dict[str, Any]]:
    """Final prompt size and mean response time, K = 10 against unbounded, with reductions."""
    out = []
    for (t, _), g in sorted(groups.items(), key=lambda kv: (task_key(kv[0][0]), column_key(kv[0][1]))):
        if g.kind != RunKind.SEARCH or g.top_k != DEFAULT_K or g.method not in PROMPT_METHODS:
            continue
        unb = groups.get((t, column_name(g.method, 0, RunKind.SEARCH)))
        if unb is None:
            continue

        def cost(grp: Group) -> tuple[float | None, float | None]:
            finals = [max((x["prompt_chars"] for x in r.calls if x["iteration"] == max(y["iteration"] for y in r.calls)), default=0)
                      for r in grp.runs if r.calls]  # fmt: skip
            lat = [x["latency_s"] for r in grp.runs for x in r.calls if x["ok"]]
            return (float(np.mean(finals)) if finals else None), (float(np.mean(lat)) if lat else None)

        (pk, lk), (pu, lu) = cost(g), cost(unb)
        red = lambda a, b: None if a is None or not b else (b - a) / b * 100.0  # noqa: E731
        out.append({"task": t, "method": g.method, "final_prompt_chars_k10": pk, "final_prompt_chars_unbounded": pu,
                    "prompt_reduction_pct": red(pk, pu), "mean_latency_s_k10": lk, "mean_latency_s_unbounded": lu,
                    "latency_reduction_pct": red(lk, lu)})  # fmt: skip
    return out


def history_cost_table(rows: list[dict[str, Any]]) -> Table | None:
    """The ``history_cost`` table of ``history_cost_rows`` (chars, seconds, %), with the paper's
    Ant-Ultra figures (Sec. IV-A) as a last row; None when there are no rows."""
    if not rows:
        return None
    f = lambda x, fmt: "" if x is None else format(x, fmt)  # noqa: E731
    header = ["Environment", "method", "final prompt K=10 (chars)", "final prompt unbounded (chars)", "prompt size reduction (%)",
              "mean response K=10 (s)", "mean response unbounded (s)", "response time reduction (%)"]  # fmt: skip
    body = [[Cell(r["task"]), Cell(r["method"]), Cell(f(r["final_prompt_chars_k10"], ",.0f")), Cell(f(r["final_prompt_chars_unbounded"], ",.0f")),
             Cell(f(r["prompt_reduction_pct"], ".1f")), Cell(f(r["mean_latency_s_k10"], ".2f")), Cell(f(r["mean_latency_s_unbounded"], ".2f")),
             Cell(f(r["latency_reduction_pct"], ".1f"))] for r in rows]  # fmt: skip
    p = pv.HISTORY_COST_TEXT
    body.append([Cell(f"paper: {p['task']}"), Cell("vanilla"), Cell(f"{p['final_prompt_chars_k10']:,}"),
                 Cell(f"{p['final_prompt_chars_unbounded']:,}"), Cell(f"{p['prompt_size_reduction_pct']}"), Cell(""), Cell(""),
                 Cell(f"{p['mean_response_time_reduction_pct']}")])  # fmt: skip
    notes = ["Final prompt: the last LLM call of each run, mean over seeds; response time: every answered call.",
             "paper: Sec. Bounded-History Analysis and Fig. fig:history_cost (gpt-oss-20b, Ant-Ultra, D = 88)."]  # fmt: skip
    return Table("history_cost", "Prompt size and LLM response time, K=10 against unbounded", header, body, notes)


def baselines_table(groups: dict[tuple[str, str], Group]) -> tuple[Table, list[dict[str, Any]]] | None:
    """Rows: methods (RL, black-box, ProPS); columns: tasks, as the paper's baselines table."""
    baselines = (MethodKind.RL, MethodKind.BLACK_BOX)
    if not any(g.method_kind in baselines for g in groups.values()):
        return None
    tasks = sorted({g.task for g in groups.values() if g.method_kind in baselines}, key=task_key)
    cols = sorted({c for (t, c), g in groups.items() if t in tasks and (g.top_k in (None, DEFAULT_K))}, key=column_key)
    stats = {k: g.stats() for k, g in groups.items() if k[0] in tasks and k[1] in cols}
    top = {t: max((s["score_mean"] for (tt, _), s in stats.items() if tt == t and s["score_mean"] is not None), default=None)
           for t in tasks}  # fmt: skip
    from ..tasks import get_task

    header = ["Approach"] + [h for t in tasks for h in (t, f"{t} paper")]
    rows, csv_rows = [], []
    for c in cols:
        row = [Cell(c)]
        for t in tasks:
            st = stats.get((t, c))
            m = find_method(c)
            algo = m.algorithm if m is not None and m.kind is MethodKind.RL else None
            if st is None:
                na = algo is not None and not algo.applies_to(get_task(t).action_type)
                row.append(Cell("--" if na else ""))
            else:
                bold = st["score_mean"] is not None and st["score_mean"] == top[t]
                row.append(Cell(_ms(st["score_mean"], st["score_std"]), bold))
                csv_rows.append({**st, "seeds": " ".join(map(str, st["seeds"])), "bold": int(bold)})
            ref = pv.main_value(t, c.split(" ")[0])
            row.append(Cell(ref.text() if ref else ""))
        rows.append(row)
    notes = ["RL: final evaluation of the trained agent (deterministic actions); search methods: search-time best. "
             "Mean (std) over seeds; best per task in bold; '--': not applicable (action space).",
             "paper: Table tab:baselines (RL, Ultra observations for Ant and Humanoid) and tab:all_results."]  # fmt: skip
    return Table("baselines", "Search methods against standard RL baselines", header, rows, notes), csv_rows


RUN_COLUMNS = ["name", "task", "method", "top_k", "seed", "status", "best", "final", "candidates", "llm_calls",
               "mean_latency_s", "final_prompt_chars", "path"]  # fmt: skip


def run_rows(runs: Sequence[RunRecord]) -> list[dict[str, Any]]:
    """One ``runs.csv`` row per run (keys ``RUN_COLUMNS``), sorted by task, column and seed.

    ``mean_latency_s`` (seconds) is over the answered LLM calls; ``final_prompt_chars`` is the
    prompt size of the last recorded call.
    """
    rows = []
    for r in sorted(runs, key=lambda r: (task_key(r.task), column_key(r.column), r.seed)):
        lat = [c["latency_s"] for c in r.calls if c["ok"]]
        rows.append({"name": r.name, "task": r.task, "method": r.column, "top_k": r.top_k, "seed": r.seed, "status": r.status,
                     "best": r.best, "final": r.final, "candidates": len(r.returns), "llm_calls": len(r.calls),
                     "mean_latency_s": float(np.mean(lat)) if lat else None,
                     "final_prompt_chars": r.calls[-1]["prompt_chars"] if r.calls else None, "path": str(r.path)})  # fmt: skip
    return rows


# -- the whole report ------------------------------------------------------------------------
def require_matplotlib() -> None:
    """Raise MissingExtraError naming the ``report`` extra when matplotlib is not installed."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as e:
        raise MissingExtraError("report", "ppprops report") from e


def write_report(root: Path, out: Path | None = None) -> Path:
    """Read every run under ``root``, write the report into ``out`` (default ``root/report``); returns ``out``.

    Runs that cannot be read are listed under ``unreadable`` in ``summary.json``, not fatal.

    Raises:
        ConfigError: ``root`` is not a directory or holds no run directory.
        MissingExtraError: matplotlib (the ``report`` extra) is not installed.
    """
    require_matplotlib()
    from ..rundir import DB_NAME, find_runs
    from . import html as html_page
    from . import plots

    root = Path(root)
    paths = find_runs(root)
    if not paths:
        raise ConfigError(f"{root} holds no run directories (no {DB_NAME} under it, nor under {root}/runs)")
    runs: list[RunRecord] = []
    unreadable: list[str] = []
    for p in paths:
        try:
            runs.append(read_run(p))
        except (StoreError, ConfigError, KeyError, ValueError) as e:
            unreadable.append(f"{p.name}: {e}")
    out = Path(out) if out is not None else root / "report"
    out.mkdir(parents=True, exist_ok=True)
    groups = group_runs(runs)
    tables: list[Table] = []
    files: list[Path] = []
    summary: dict[str, Any] = {"root": str(root.resolve()), "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
                               "runs": len(runs), "done": sum(r.done for r in runs), "unreadable": unreadable}  # fmt: skip
    built = main_table(groups)
    if built:
        tables.append(built[0])
        files += write_table(out, built[0], built[1], STAT_COLUMNS)
        summary["main_results"] = built[1]
    built = bounded_table(groups)
    if built:
        tables.append(built[0])
        cols = list(built[1][0].keys())
        files += write_table(out, built[0], built[1], cols)
        summary["bounded_history"] = built[1]
    cost_rows = history_cost_rows(groups)
    cost = history_cost_table(cost_rows)
    if cost:
        tables.append(cost)
        files += write_table(out, cost, cost_rows, list(cost_rows[0].keys()))
        summary["history_cost"] = cost_rows
    built = baselines_table(groups)
    if built:
        tables.append(built[0])
        files += write_table(out, built[0], built[1], STAT_COLUMNS)
        summary["baselines"] = built[1]
    rows = run_rows(runs)
    write_csv(out / "runs.csv", rows, RUN_COLUMNS)
    curve_images = plots.reward_curves(out, groups)
    cost_images = plots.history_cost(out, groups, retained_history)
    summary["images"] = [p.name for p in curve_images + cost_images]
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str), encoding="utf-8")
    html_page.write_index(out, title=f"ppprops report: {root.resolve().name}", summary=summary, tables=tables,
                          curve_images=curve_images, cost_images=cost_images, runs=rows)  # fmt: skip
    return out
