"""Baselines stored as ordinary runs: standard RL agents (``rl``) next to the black-box proposers.

Nothing here imports torch at package import: ``algorithms`` and ``record`` are plain data and
SQLite, so ``ppprops show`` and ``ppprops --help`` work without the ``rl`` extra; only ``sb3``
(imported by ``rl`` when training starts) needs it.
"""
