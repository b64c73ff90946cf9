"""The paper's tasks as task files: the ten configurations of its table of evaluated environments,
plus the documented Highway-Fast preset. They are the same kind of file a user writes
(``ppprops run --task-file``; see docs/own-robot.md), with two extras only ppprops' own files use:
``recorder`` (code that derives feedback from each step) and ``setup`` (a simulator-extra check).
"""

from __future__ import annotations

# In the order `ppprops envs` lists them.
TASK_FILES = (
    "ant-ultra.toml",
    "ant-joints.toml",
    "ant-torso.toml",
    "humanoid-ultra.toml",
    "humanoid-joints.toml",
    "humanoid-torso.toml",
    "cartpole.toml",
    "acrobot.toml",
    "fetch-reach-dense.toml",
    "highway.toml",
)
# Reached by name only: "highway-v0" keeps meaning the paper's Highway task.
PRESET_FILES = ("highway-fast.toml",)
