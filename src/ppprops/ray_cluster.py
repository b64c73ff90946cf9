"""Reaching Ray: the one place ppprops imports it and joins or starts a cluster.

``--ray-address local`` (and a grid's ``--ray local``) starts a private Ray instance on this
machine. Ray starts its worker processes at niceness 15 by default, so anything else running on
the machine (another search, the test suite, a benchmark) takes the cores first and a run's
embedded llama.cpp server, a child of its worker, slows down many times over (measured here: a
request of 3.4 s in a local process took 48 s in a Ray task on 2 busy cores). A private instance
therefore starts its workers at niceness 0, like the local processes of ``--workers`` and of a
local grid. A cluster that ppprops joins keeps the niceness its operator chose.
"""

from __future__ import annotations

import os
from typing import Any

from .errors import ConfigError, MissingExtraError

WORKER_NICENESS = 0  # of the workers of a private instance (Ray's own default: 15)


def import_ray(flag: str) -> Any:
    """The ``ray`` module.

    Args:
        flag: the option that asked for Ray, named in the error.

    Raises:
        MissingExtraError: the ``ray`` extra is not installed.
    """
    try:
        import ray
    except ImportError as e:
        raise MissingExtraError("ray", flag) from e
    return ray


def connect(address: str, flag: str) -> tuple[Any, bool]:
    """Join the cluster at ``address`` (``auto``, ``HOST:6379``, ``ray://HOST:10001``), or start a
    private instance with every core of this machine for ``local``; nothing when this process is
    already connected.

    Args:
        address: where the cluster is, or ``local``.
        flag: the option that gave it, named in errors (``--ray-address``).

    Returns:
        (the ``ray`` module, whether this call started the connection: the caller shuts it down).

    Raises:
        MissingExtraError: the ``ray`` extra is not installed.
        ConfigError: the cluster cannot be reached (one line).
    """
    ray = import_ray(flag)
    if ray.is_initialized():
        return ray, False
    kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    if address == "local":
        kw["num_cpus"] = os.cpu_count() or 1
        kw["_system_config"] = {"worker_niceness": WORKER_NICENESS}
    else:
        kw["address"] = address
    try:
        ray.init(**kw)
    except (ConnectionError, RuntimeError, ValueError) as e:
        detail = str(e).splitlines()[0] if str(e) else "no detail"
        raise ConfigError(f"{flag} {address}: cannot reach a Ray cluster ({type(e).__name__}: {detail})") from None
    return ray, True
