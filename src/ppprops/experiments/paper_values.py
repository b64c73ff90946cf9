"""The paper's reported numbers, transcribed as data, for reference columns beside ours.

Source: /work/shared/paper/pp-props-paper.tex (mean (std) over five runs; gpt-oss-20b, 10 warm-up
policies, 50 LLM iterations, K = 10 unless stated). Each value names the table it comes from.
Task names are ppprops names: the paper's "Highway Env" is ``Highway``, and its baselines table's
"Ant"/"Humanoid" columns are the Ultra observation configurations, as its text states.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PaperValue:
    """One number of the paper: mean (std) over its five runs, in the task's raw reward units.

    ``table`` is the LaTeX label it is printed under; ``note`` a footnote (or why there is no number).
    """

    mean: float | None  # None: the paper reports no number (note says why)
    std: float | None
    table: str  # LaTeX label of the table (or figure) the value is printed in
    note: str = ""

    def text(self) -> str:
        """As a table cell: ``mean (std)``, `` †`` after it when there is a note; the note alone
        (or "n/a") when the paper has no number."""
        if self.mean is None:
            return self.note or "n/a"
        mark = " †" if self.note else ""
        return f"{self.mean:g} ({self.std:g}){mark}" if self.std is not None else f"{self.mean:g}{mark}"


ALL_RESULTS = "tab:all_results"
BOUNDED = "tab:bounded_history_performance"
BASELINES = "tab:baselines"
HISTORY_COST = "fig:history_cost"

_OVERFLOW = "context overflow"
# tab:all_results, columns Vanilla ProPS, R2PO, PE-ProPS, DF-ProPS, PP-ProPS
_MAIN: dict[str, tuple[tuple[float | None, float | None], ...]] = {
    "Ant-Ultra": ((942.75, 59.11), (None, None), (998.64, 4.75), (998.9, 37.5), (994.55, 10.72)),
    "Ant-Joints": ((966.58, 48.61), (None, None), (982.62, 26.45), (996.15, 2.79), (989.68, 17.11)),
    "Ant-Torso": ((929.19, 61.73), (None, None), (982.41, 28.62), (993.76, 0.27), (997.08, 7.69)),
    "Humanoid-Ultra": ((448.2, 51.65), (443.7, 80.5), (382.51, 73.79), (475.91, 72.61), (375.52, 96.64)),
    "Humanoid-Joints": ((394.38, 90.88), (293.2, 77.1), (364.5, 94.03), (387.0, 69.3), (361.59, 97.2)),
    "Humanoid-Torso": ((307.38, 63.7), (260.92, 20.74), (251.0, 54.93), (326.43, 87.67), (290.68, 43.57)),
    "Acrobot": ((-77.6, 1.39), (-83.5, 4.6), (-77.4, 0.2), (-71.6, 0.4), (-73.3, 1.12)),
    "CartPole": ((495.0, 10.0), (500.0, 0.0), (494.8, 6.5), (495.2, 10.0), (499.9, 0.2)),
    "FetchReachDense": ((-0.6, 0.03), (-0.61, 0.07), (-0.78, 0.06), (-0.51, 0.05), (-0.54, 0.03)),
    "Highway": ((122.57, 24.25), (146.2, 1.4), (90.04, 18.86), (151.46, 4.16), (154.55, 10.33)),
}
_MAIN_METHODS = ("vanilla", "r2po", "pe", "df", "pp")
_R2PO_TORSO_NOTE = "three of five runs stopped early by context overflow; best pre-overflow policies"

# tab:baselines: RL algorithms on Ant(-Ultra), Humanoid(-Ultra), Acrobot, CartPole, Highway, FetchReachDense
_BASELINE_TASKS = ("Ant-Ultra", "Humanoid-Ultra", "Acrobot", "CartPole", "Highway", "FetchReachDense")
_RL: dict[str, tuple[tuple[float, float] | None, ...]] = {
    "rl-ppo": ((1000.16, 15.06), (192.94, 16.38), (-303.95, 170.33), (127.16, 179.77), (107.01, 26.51), (-7.65, 0.46)),
    "rl-a2c": ((233.61, 126.42), (118.82, 75.77), (-209.57, 158.84), (161.69, 177.61), (73.68, 33.65), (-12.80, 8.19)),
    "rl-sac": ((-52.42, 46.51), (78.24, 3.10), None, None, None, (-8.55, 0.99)),
    "rl-td3": ((938.04, 240.49), (81.86, 34.78), None, None, None, (-8.06, 1.79)),
    "rl-ddpg": ((-6.55, 72.99), (89.59, 40.25), None, None, None, (-7.39, 2.45)),
    "rl-trpo": ((965.23, 10.99), (193.21, 16.80), (-284.65, 171.60), (127.04, 187.54), (109.09, 30.69), (-8.76, 0.93)),
    "rl-dqn": (None, None, (-408.80, 150.13), (12.51, 5.98), (39.14, 4.31), None),
}

# tab:bounded_history_performance: Vanilla ProPS on Ant, K = 10 vs unbounded, Diff (%)
BOUNDED_ROWS: dict[str, tuple[int, tuple[float, float], tuple[float, float], float]] = {
    "Ant-Ultra": (88, (942.75, 59.11), (950.75, 32.1), -0.84),
    "Ant-Joints": (136, (966.58, 48.61), (966.9, 15.7), -0.03),
    "Ant-Torso": (224, (929.19, 61.73), (932.7, 53.7), -0.38),
}

# fig:history_cost and Sec. "Bounded-History Analysis" (Ant-Ultra, D = 88)
HISTORY_COST_TEXT = {
    "task": "Ant-Ultra",
    "final_prompt_chars_unbounded": 114_000,
    "final_prompt_chars_k10": 22_000,
    "prompt_size_reduction_pct": 80.2,
    "mean_response_time_reduction_pct": 74.9,
}


def main_value(task: str, method: str, top_k: int = 10) -> PaperValue | None:
    """The paper's number for ``method`` on ``task`` (tab:all_results; unbounded vanilla from
    tab:bounded_history_performance; RL algorithms from tab:baselines)."""
    if top_k == 0:
        row = BOUNDED_ROWS.get(task)
        if method == "vanilla" and row is not None:
            return PaperValue(row[2][0], row[2][1], BOUNDED)
        return None
    if top_k != 10:
        return None
    if method in _MAIN_METHODS and task in _MAIN:
        mean, std = _MAIN[task][_MAIN_METHODS.index(method)]
        if mean is None:
            return PaperValue(None, None, ALL_RESULTS, _OVERFLOW)
        note = _R2PO_TORSO_NOTE if (task, method) == ("Humanoid-Torso", "r2po") else ""
        return PaperValue(mean, std, ALL_RESULTS, note)
    if method in _RL and task in _BASELINE_TASKS:
        cell = _RL[method][_BASELINE_TASKS.index(task)]
        return PaperValue(None, None, BASELINES, "--") if cell is None else PaperValue(cell[0], cell[1], BASELINES)
    return None


def bounded_value(task: str) -> tuple[int, PaperValue, PaperValue, float] | None:
    """(D, K = 10, unbounded, Diff %) of tab:bounded_history_performance, for vanilla on ``task``."""
    row = BOUNDED_ROWS.get(task)
    if row is None:
        return None
    D, k10, unb, diff = row
    return D, PaperValue(k10[0], k10[1], BOUNDED), PaperValue(unb[0], unb[1], BOUNDED), diff
