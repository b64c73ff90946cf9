"""11. Does the small model keep its place with one label per row?

The document form labels values so the embedded model can copy a value from the same coordinate
of an entry above. The grid format labels only the first value of each row of W (and of the
biases); this benchmark asks the embedded model to continue the same final document (the real
Ant-Ultra history of benchmark 1, D=88, K=10, and an Acrobot one, D=21) with a label on every value
and with one per row, at the document form's temperatures (0.6 and 1.0), through the form's own
request (its grammar), and measures where each value it writes lands:

- in column: the value lies within the range the shown entries print at its coordinate, widened by
  a quarter of that range on each side (a model that lost its place writes values of a neighbouring
  coordinate, whose scale differs by the secret a_j: up to 100 times);
- shifted by one: the same test for the coordinate next to it (what a model one place off would score);
- copied: the value equals the best shown entry's at that coordinate;
- correlation with the best shown entry across coordinates, in place and moved one place.

Answer tokens come from llama.cpp's own count.
"""

from __future__ import annotations

import json
import statistics
from dataclasses import replace
from typing import Any

import numpy as np
from _common import Context, Section, _proposer, config, embedded, run_search, table, timings

from ppprops.wire import numbers
from ppprops.wire.forms import DOCUMENT

SAMPLES = 4  # continuations per (task, labels); iterations 0..3 use the schedule's 0.6, 1.0, 0.6, 1.0
ROWS = replace(numbers.GRID, name="grid-rows", row_labels=True)  # the grid with one label per row of W


def _history(ctx: Context, task: str) -> Any:
    if task == "Ant-Ultra" and (ctx.dir("prompt") / "ant-history" / "run.sqlite").exists():
        return ctx.dir("prompt") / "ant-history"
    return run_search(config(task, warmup=12 if ctx.quick else 30, iterations=0, seed=1, select_top=0), ctx.dir("labels") / task)


def _scores(values: list[float], shown: list[tuple[float, ...]]) -> tuple[float, float, float, float, float]:
    cols = np.array(shown)
    lo, hi = cols.min(axis=0), cols.max(axis=0)
    pad = 0.25 * np.maximum(hi - lo, 1.0)
    x = np.asarray(values)
    inside = (x >= lo - pad) & (x <= hi + pad)
    shifted = (x[1:] >= (lo - pad)[:-1]) & (x[1:] <= (hi + pad)[:-1])
    copied = np.rint(x) == np.rint(cols[-1])
    same = float(np.corrcoef(x, cols[-1])[0, 1])  # with the best entry, coordinate by coordinate
    off = float(np.corrcoef(x[1:], cols[-1][:-1])[0, 1])  # with the best entry moved one place
    return float(inside.mean()), float(shifted.mean()), float(copied.mean()), same, off


def run(ctx: Context) -> Section:
    numbers.NUMBER_FORMATS[ROWS.name] = ROWS
    rows, data = [], {}
    samples = 2 if ctx.quick else SAMPLES
    try:
        with embedded() as client:
            for task in ("Acrobot", "Ant-Ultra"):
                run_dir = _history(ctx, task)
                for fmt, label in (("grid", "every value"), (ROWS.name, "one per row")):
                    prop, cands = _proposer(run_dir, 10, "document", number_format="grid")  # the grid's codec
                    prop.ctx = replace(prop.ctx, number_format=fmt)  # and its labels
                    for c in cands:
                        prop.tell(c)
                    shown = prop.shown()
                    pctx = prop.ctx
                    prompt = DOCUMENT.prompt(pctx, shown)
                    per: list[dict[str, float]] = []
                    for it in range(samples):
                        req = DOCUMENT.request(prompt, ctx=pctx, shown=shown, iteration=it, attempt=0)
                        ex = client.send(req, seed=1000 + it)
                        res = DOCUMENT.read(ex.content, pctx.D, finish_reason=ex.finish_reason)
                        t = timings(ex.response)
                        n_tok = t.get("predicted_n", float("nan"))
                        if res.values is None:
                            per.append({"ok": 0.0, "tokens_per_param": n_tok / pctx.D})
                            continue
                        inside, shifted, copied, same, off = _scores(list(res.values), [e.params for e in shown])
                        per.append({"ok": 1.0, "in_column": inside, "shifted": shifted, "copied": copied, "corr": same,
                                    "corr_shifted": off, "tokens_per_param": n_tok / pctx.D})
                    ok = [p for p in per if p["ok"]]
                    agg = {k: statistics.fmean(p[k] for p in ok) if ok else float("nan") for k in ("in_column", "shifted", "copied", "corr", "corr_shifted")}
                    agg["tokens_per_param"] = statistics.fmean(p["tokens_per_param"] for p in per)
                    agg["usable"] = len(ok)
                    data[f"{task}_{label}"] = {**agg, "samples": per}
                    rows.append([task, pctx.D, label, f"{len(ok)}/{len(per)}", f"{agg['in_column']:.0%}", f"{agg['shifted']:.0%}",
                                 f"{agg['copied']:.0%}", f"{agg['corr']:.2f} / {agg['corr_shifted']:.2f}", f"{agg['tokens_per_param']:.2f}"])
    finally:
        numbers.NUMBER_FORMATS.pop(ROWS.name, None)
    body = [
        f"The final document (K=10) of a real history, continued {samples} times per row by the embedded model through the "
        "document form's request (its grammar; temperatures 0.6, 1.0, ...); grid format, labels on every value vs one per row.",
        "",
        table(["task", "D", "labels", "usable answers", "values in their column's range", "... in the next column's",
               "copied from the best", "correlation with the best, same place / one off", "answer tokens/param (llama.cpp)"], rows),
    ]
    return Section("labels", "11. Labels in the document form: does the model keep its place?", "\n".join(body),
                   json.loads(json.dumps(data, default=float)))
