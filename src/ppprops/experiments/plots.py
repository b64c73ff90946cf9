"""The paper's two figures, per task: reward curves (fig:optimization_performance) and LLM
response time against retained history and prompt size (fig:history_cost). matplotlib, Agg."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..status import RunKind
from .order import PROMPT_METHODS, column_key, task_key

if TYPE_CHECKING:
    from .records import Group, RunRecord


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # files only: no display, no GUI toolkit
    import matplotlib.pyplot as plt

    return plt


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", text)


def curve(runs: list[RunRecord]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x (warm-up at -W..-1, LLM iterations from 0), mean and std over seeds of the candidate's return."""
    warm = max(r.warmup for r in runs)
    length = max(len(r.returns) for r in runs)
    y = np.full((len(runs), length), np.nan)
    for i, r in enumerate(runs):
        shift = warm - r.warmup
        for j, v in enumerate(r.returns):
            if v is not None and j + shift < length:
                y[i, j + shift] = v
    with np.errstate(all="ignore"):
        counts = np.sum(~np.isnan(y), axis=0)
        mean = np.where(counts > 0, np.nansum(y, axis=0) / np.maximum(counts, 1), np.nan)
        std = np.sqrt(np.where(counts > 0, np.nansum((y - mean) ** 2, axis=0) / np.maximum(counts, 1), np.nan))
    return np.arange(length) - warm, mean, std


def reward_curves(out: Path, groups: dict[tuple[str, str], Group]) -> list[Path]:
    """One PNG per task: each method's mean return per iteration with a shaded +-std band."""
    plt = _plt()
    paths = []
    tasks = sorted({t for (t, _), g in groups.items() if g.kind == RunKind.SEARCH}, key=task_key)
    for task in tasks:
        cols = sorted((c for (t, c), g in groups.items() if t == task and g.kind == RunKind.SEARCH), key=column_key)
        fig, ax = plt.subplots(figsize=(7.0, 4.2), dpi=110)
        warm = 0
        for c in cols:
            runs = [r for r in groups[(task, c)].runs if r.returns]
            if not runs:
                continue
            x, mean, std = curve(runs)
            warm = max(warm, -int(x[0]))
            line = ax.plot(x, mean, label=f"{c} (n={len(runs)})", lw=1.6)[0]
            ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.18, lw=0)
        if warm:
            ax.axvspan(-warm - 0.5, -0.5, color="0.85", alpha=0.5, lw=0)
            ax.axvline(-0.5, color="0.4", ls="--", lw=1)
            ax.text(-warm / 2 - 0.5, 0.98, "warm-up", transform=ax.get_xaxis_transform(), ha="center", va="top", fontsize=8)
        ax.set_xlabel("iteration (warm-up before 0)")
        ax.set_ylabel("episodic return")
        ax.set_title(f"{task}: mean return, shaded ±1 std over seeds")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
        fig.tight_layout()
        path = out / f"curves_{_slug(task)}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths


def history_cost(out: Path, groups: dict[tuple[str, str], Group], retained: Callable[[RunRecord, int], int]) -> list[Path]:
    """One PNG per task with prompt-based LLM runs: response time against retained history size
    (left) and prompt size (right), one colour per history setting; the large marker is each
    setting's mean over its last iteration (the paper highlights K = 10 and unbounded)."""
    plt = _plt()
    paths = []
    tasks = sorted({t for (t, _), g in groups.items() if g.method in PROMPT_METHODS and any(r.calls for r in g.runs)}, key=task_key)
    for task in tasks:
        cols = sorted((c for (t, c), g in groups.items() if t == task and g.method in PROMPT_METHODS), key=column_key)
        fig, (left, right) = plt.subplots(1, 2, figsize=(9.5, 4.0), dpi=110, sharey=True)
        for c in cols:
            pts = [(retained(r, x["iteration"]), x["prompt_chars"], x["latency_s"], x["iteration"] == r.calls[-1]["iteration"])
                   for r in groups[(task, c)].runs for x in r.calls if x["ok"]]  # fmt: skip
            if not pts:
                continue
            h, p, lat, last = (np.array(v) for v in zip(*pts))
            sc = left.scatter(h, lat, s=10, alpha=0.5, label=c)
            right.scatter(p, lat, s=10, alpha=0.5, color=sc.get_facecolor()[0])
            if last.any():
                kw = {"s": 140, "marker": "*", "edgecolor": "k", "linewidth": 0.8, "color": sc.get_facecolor()[0], "zorder": 3}
                left.scatter([h[last].mean()], [lat[last].mean()], **kw)
                right.scatter([p[last].mean()], [lat[last].mean()], **kw)
        left.set_xlabel("retained history size (entries in the prompt)")
        right.set_xlabel("prompt size (characters)")
        left.set_ylabel("LLM response time (s)")
        for ax in (left, right):
            ax.grid(alpha=0.3)
        left.legend(fontsize=8)
        fig.suptitle(f"{task}: LLM response time against history and prompt size (★: last iteration, mean)")
        fig.tight_layout()
        path = out / f"history_cost_{_slug(task)}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths
