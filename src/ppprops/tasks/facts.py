"""A task's privacy facts: what a curious provider may know about it without any secret (issue 20).

The facts live with the task: a task file's ``[privacy]`` table (``tasks.schema.PrivacyTable``)
becomes a ``PrivacyFacts`` on its ``TaskSpec``, stored with every run. Each fact is either declared
or unknown (``None``); ``False`` in a name, formula, range or time-limit fact states that the task
has none, which is known. ``ppprops.privacy.knowledge.facts_for`` turns them into the attacks'
``PublicFacts`` together with the list of facts that are unknown, and ``client.hardening`` reads
the hardened preset's facts (what it hides, the bound of its secret offsets) from them.

The facts and what uses them (docs/threat-model.md):

==========================  =====================================================================
``public_env``              an attacker can build and simulate the env (simulator attacks)
``integer_returns``         every per-step reward is an integer (lattice attacks)
``return_formula``          raw return = sum(coef x diagnostic) + ``return_formula_constant``
``caps``                    returns a marked episode end pins: (side, value, diagnostic, marker)
``return_range``            public [low, high] of one episode's return
``resolution``              public step of each reward quantity ("return" or a component);
                            the hardened codec dithers below it
``survive_component``       the component paid ``healthy_reward`` per step while alive
``ctrl_component``          the control cost; a saturated controller costs ``ctrl_per_step``
``time_limit``              steps after which every episode ends
``components_sum_to_return``  the components add up to the return exactly
``return_determining``      diagnostics that pin the return (hidden by pp-hardened)
``residual_component``      the component pp-hardened leaves out (closes additivity)
``reward_scale``            public magnitude of returns: bound of the secret offsets (reward units)
==========================  =====================================================================
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal

Cap = tuple[str, float, str, str]  # (side "max" | "min", pinned return, diagnostic that marks it, its value there)

# Facts in the order the docs list them; ``return_formula_constant`` belongs to ``return_formula``.
FACT_NAMES = ("public_env", "integer_returns", "return_formula", "return_formula_constant", "caps", "return_range",
              "resolution", "survive_component", "healthy_reward", "ctrl_component", "ctrl_per_step", "time_limit",
              "components_sum_to_return", "return_determining", "residual_component", "reward_scale")  # fmt: skip


@dataclass(frozen=True)
class PrivacyFacts:
    """The declared privacy facts of one task; ``None`` is unknown (see the module docstring for each)."""

    public_env: bool | None = None
    integer_returns: bool | None = None
    return_formula: Mapping[str, float] | Literal[False] | None = None
    return_formula_constant: float | None = None
    caps: tuple[Cap, ...] | None = None
    return_range: tuple[float, float] | Literal[False] | None = None
    resolution: Mapping[str, float] | None = None
    survive_component: str | Literal[False] | None = None
    healthy_reward: float | None = None
    ctrl_component: str | Literal[False] | None = None
    ctrl_per_step: float | None = None
    time_limit: int | Literal[False] | None = None
    components_sum_to_return: bool | None = None
    return_determining: tuple[str, ...] | None = None
    residual_component: str | Literal[False] | None = None
    reward_scale: float | None = None

    def unknown(self) -> tuple[str, ...]:
        """The facts not declared, in ``FACT_NAMES`` order.

        A fact that only refines another is counted only where that other one makes it matter:
        ``healthy_reward`` when ``survive_component`` names a component, ``ctrl_per_step`` when
        ``ctrl_component`` does; ``return_formula_constant`` (0 by default) and ``public_env``
        (``TaskSpec.public_env`` decides it when not declared) never.
        """
        out = []
        for name in FACT_NAMES:
            if name in ("return_formula_constant", "public_env") or getattr(self, name) is not None:
                continue
            if name == "healthy_reward" and not self.survive_component:
                continue
            if name == "ctrl_per_step" and not self.ctrl_component:
                continue
            out.append(name)
        return tuple(out)

    def is_empty(self) -> bool:
        """True when nothing is declared."""
        return all(getattr(self, f.name) is None for f in fields(self))

    def to_json(self) -> dict[str, Any]:
        """The declared facts as JSON values (absent keys are unknown facts)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if f.name == "caps":
                v = [{"side": s, "value": val, "diagnostic": d, "marker": m} for s, val, d, m in v]
            elif isinstance(v, Mapping):
                v = dict(v)
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> PrivacyFacts:
        """The inverse of ``to_json`` (also reads ``PrivacyTable.model_dump()``). KeyError/TypeError/ValueError when damaged."""
        kw: dict[str, Any] = {}
        for name, v in d.items():
            if name not in FACT_NAMES:
                raise ValueError(f"unknown privacy fact {name!r}")
            if v is None or v is False:
                kw[name] = v
            elif name == "caps":
                kw[name] = tuple((str(c["side"]), float(c["value"]), str(c["diagnostic"]), str(c["marker"])) for c in v)
            elif name in ("return_formula", "resolution"):
                kw[name] = {str(k): float(x) for k, x in v.items()}
            elif name == "return_range":
                lo, hi = v
                kw[name] = (float(lo), float(hi))
            elif name == "return_determining":
                kw[name] = tuple(str(x) for x in v)
            elif name in ("public_env", "integer_returns", "components_sum_to_return"):
                kw[name] = bool(v)
            elif name == "time_limit":
                kw[name] = int(v)
            elif name in ("survive_component", "ctrl_component", "residual_component"):
                kw[name] = str(v)
            else:
                kw[name] = float(v)
        return cls(**kw)


__all__ = ["FACT_NAMES", "Cap", "PrivacyFacts"]
