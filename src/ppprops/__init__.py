"""ppprops: Privacy-Preserving Prompted Policy Search (PP-ProPS).

An LLM proposes linear-policy parameters from an encoded history; the client keeps the policy,
the rewards and the secrets. The Python API (``ppprops.api``, loaded on first use so that
``import ppprops`` stays light):

    result = ppprops.search("CartPole", method="pp", iterations=50, out="runs/x")
    with ppprops.create_study("robot.toml", storage="study/") as study:   # your robot drives it
        trial = study.ask(); study.tell(trial, episode_return)
    policy = ppprops.load_policy("runs/x/best_policy.json")   # raw observation -> action
    ppprops.evaluate_policy(policy, episodes=20, seed=0)
    ppprops.resume("runs/x"); ppprops.load_run("runs/x")
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .version import __version__

_API = ("search", "resume", "load_run", "evaluate_policy", "load_policy", "create_study", "load_study", "SearchResult", "Evaluation",
        "Policy", "Study")
__all__ = ["__version__", *_API]

if TYPE_CHECKING:
    from .api import (  # noqa: F401
        Evaluation,
        Policy,
        SearchResult,
        Study,
        create_study,
        evaluate_policy,
        load_policy,
        load_run,
        load_study,
        resume,
        search,
    )


def __getattr__(name: str) -> Any:
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'ppprops' has no attribute {name!r}")
