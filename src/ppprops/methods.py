"""The paper's four configurations as combinations of independent privacy/feedback mechanisms."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from .errors import ConfigError


@dataclass(frozen=True)
class Mechanisms:
    """Each switch is one mechanism of Section II; presets are named combinations of them."""

    encode_params: bool  # theta~ = A theta in the prompt (Sec. II-B)
    scale_rewards: bool  # r~ = c r for the return and every reward component (Sec. II-C)
    detailed_feedback: bool  # reward components and diagnostics in the history (Sec. II-C)
    disclose_optimum: bool  # the optimal return stated as a target (Vanilla ProPS)
    disclose_reward_structure: bool  # the numeric reward definition (per-step values, limits)

    def to_json(self) -> dict[str, bool]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Mechanisms:
        return cls(**{k: bool(d[k]) for k in cls.__dataclass_fields__})


PRESETS: dict[str, Mechanisms] = {
    # Vanilla ProPS: raw parameters, scalar return, reward structure and optimum disclosed.
    "vanilla": Mechanisms(False, False, False, True, True),
    # PE-ProPS: as vanilla, with encoded parameters.
    "pe": Mechanisms(True, False, False, True, True),
    # DF-ProPS: as vanilla, plus component rewards and diagnostics on raw values.
    "df": Mechanisms(False, False, True, True, True),
    # PP-ProPS: encoded parameters, scaled rewards, detailed feedback, no optimum. The numeric
    # reward definition is withheld too, because it states the optimum (e.g. 500 steps x +1).
    "pp": Mechanisms(True, True, True, False, False),
}


def resolve(method: str, **overrides: bool | None) -> Mechanisms:
    """A preset, with any mechanism switched on or off individually."""
    if method not in PRESETS:
        raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(PRESETS)}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    unknown = set(changes) - set(Mechanisms.__dataclass_fields__)
    if unknown:
        raise ConfigError(f"unknown mechanism(s): {', '.join(sorted(unknown))}")
    return replace(PRESETS[method], **changes)
