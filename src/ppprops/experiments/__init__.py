"""Experiment grids (tasks x methods x seeds) and the paper's tables and figures from them.

``ppprops experiment SPEC --out DIR`` expands a spec (``spec``) into named runs, derives each
run's secrets from the grid's master key (``grid``), and executes the runs in local processes
(``execute_local``) or on Ray (``execute_ray``); rerunning the command continues the grid.
``ppprops report DIR`` turns the finished runs into tables, curves and ``index.html``
(``report``). This package imports nothing heavy: the CLI builds its parsers from it.
"""
