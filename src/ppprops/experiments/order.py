"""The order of the paper's tables and figures: its tasks, the registry's methods, the default K.

``report`` (tables) and ``plots`` (figures) both sort by these keys; they live here so that
neither imports the other.
"""

from __future__ import annotations

from ..methods import methods

PAPER_TASKS = ("Ant-Ultra", "Ant-Joints", "Ant-Torso", "Humanoid-Ultra", "Humanoid-Joints", "Humanoid-Torso",
               "Acrobot", "CartPole", "FetchReachDense", "Highway")  # fmt: skip
METHOD_ORDER = tuple(m.name for m in methods())  # the registry's order: the paper's tables
PROMPT_METHODS = tuple(m.name for m in methods() if m.top_k_prompt)  # one LLM call per iteration over a top-K history
DEFAULT_K = 10  # the paper's history bound (Sec. III): a column with K = 10 needs no mark


def column_key(col: str) -> tuple[int, str]:
    """Sort key of a table column: the paper's method order first, then the column name."""
    base = col.split(" ")[0]
    return (METHOD_ORDER.index(base) if base in METHOD_ORDER else len(METHOD_ORDER), col)


def task_key(task: str) -> tuple[int, str]:
    """Sort key of a task: the paper's task order first, then the task name."""
    return (PAPER_TASKS.index(task) if task in PAPER_TASKS else len(PAPER_TASKS), task)
