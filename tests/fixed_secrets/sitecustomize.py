"""Test-only seam: fixed secrets, run id and run seed in a child process (the ``ppprops`` command
line run by a test in a subprocess), where a test's monkeypatch cannot reach.

A test puts this folder first on ``PYTHONPATH`` and sets ``PPPROPS_TEST_SECRETS_SEED`` to an
integer; Python then imports this module at start-up (``site``), and it makes every run this
process creates draw its secrets from ``numpy.random.default_rng(seed)`` instead of the operating
system's entropy source (``ppprops.client.secrets.os_rng``, as ``hardening.generate_secrets`` calls
it), take the run id ``<task>__<method>__<seed>__20261204-000000-0000`` (``naming.new_run_id``,
which ``rundir.new_run_id`` and default run directories use) and, given no ``--seed``, a run seed
drawn from the same seed, above the provider's seed search (``seeding.draw_seed``; below 2^16 it
is read off the transcript: ``privacy.runseed``). A test that asserts an audit's verdict then
gets the same verdict on every run: on fresh secrets an attack reads a value by chance in a few
runs of a hundred. Without the variable this module does nothing; with a variable it cannot apply
(not an integer, ppprops not importable) the process stops at start-up.

Never on the path outside the tests: a run made with it has secrets anyone can draw again.
"""

from __future__ import annotations

import os

SEED_ENV = "PPPROPS_TEST_SECRETS_SEED"
RUN_TIME = "20261204-000000-0000"  # the fixed "<time>-<4 hex digits>" tail of the run id


def _install(fixed: int) -> None:
    import numpy as np

    from ppprops import naming, seeding
    from ppprops.client import hardening, secrets

    def fixed_rng() -> np.random.Generator:
        return np.random.default_rng(fixed)

    def fixed_run_id(task: str, method: str, seed: int) -> str:
        return f"{naming.safe_name(task)}__{method}__{seed}__{RUN_TIME}"

    def fixed_run_seed() -> int:
        return int(np.random.default_rng([fixed, 1]).integers(1 << 16, 1 << 31))

    secrets.os_rng = fixed_rng  # Secrets.generate / generate_hardened without an rng
    hardening.os_rng = fixed_rng  # generate_secrets, the routine every run draws its secrets with
    naming.new_run_id = fixed_run_id
    seeding.draw_seed = fixed_run_seed  # looked up when called (cli, api)


_value = os.environ.get(SEED_ENV)
if _value:
    try:
        _install(int(_value))
    except Exception as e:  # site would print this and go on with fresh secrets: stop the process instead
        raise SystemExit(f"tests/fixed_secrets: cannot fix the secrets ({SEED_ENV}={_value!r}): {e!r}") from e
