"""The paper's four configurations as combinations of independent privacy/feedback mechanisms.

``pp-hardened`` adds five switches that close the side channels measured in
docs/threat-model.md; the four paper presets keep every new switch off, so they behave exactly
as the paper defines them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
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
    # Hardening (docs/threat-model.md); all off in the paper's presets.
    secret_offsets: bool = False  # theta~ = A (theta - m), r~ = c (r - s): secret raw origins m, s
    warp_params: bool = False  # theta~ = A T(theta): the public box mapped onto the whole real line
    warp_rewards: bool = False  # r~ = c w_p(r): a secret increasing power warp instead of a pure scale
    hide_return_diagnostics: bool = False  # drop diagnostics that pin the return or a reward component
    encoded_warmup: bool = False  # warm-up drawn uniformly in the encoded space, then decoded

    def to_json(self) -> dict[str, bool]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Mechanisms:
        """Reads stored configs, including those written before the hardening switches existed."""
        values: dict[str, bool] = {}
        for f in fields(cls):
            if f.name in d:
                values[f.name] = bool(d[f.name])
            elif f.default is False:
                values[f.name] = False
            else:
                raise KeyError(f.name)
        return cls(**values)

    @property
    def hardened(self) -> bool:
        """True when any hardening switch is on (the secrets then carry offsets and a warp exponent)."""
        return any(getattr(self, k) for k in HARDENING)

    def check(self) -> None:
        """Combinations that would reveal the secrets they are meant to hide are refused."""
        if (self.warp_params or self.encoded_warmup) and not self.encode_params:
            raise ConfigError("--warp-params and --encoded-warmup need --encode-params on")
        if self.encoded_warmup and not self.warp_params:
            # decoding a public encoded box through theta/a_j leaves the raw box for a_j < 1, and the
            # clipped values re-encode to +-6 a_j: the warm-up would state A instead of hiding it
            raise ConfigError("--encoded-warmup needs --warp-params on (an affine map would clip the warm-up to the box edges)")
        if self.warp_rewards and not self.scale_rewards:
            raise ConfigError("--warp-rewards needs --scale-rewards on")
        if self.secret_offsets and not (self.encode_params or self.scale_rewards):
            raise ConfigError("--secret-offsets needs --encode-params or --scale-rewards on")


HARDENING = ("secret_offsets", "warp_params", "warp_rewards", "hide_return_diagnostics", "encoded_warmup")

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
    # PP-ProPS with the side channels of docs/threat-model.md closed (not a configuration of the paper).
    "pp-hardened": Mechanisms(True, True, True, False, False, True, True, True, True, True),
}


# Methods whose prompts show the provider raw trajectory evidence: R2PO's critic reads raw states and
# the actions the policy took in them. For a linear policy u = W^T s + b a least-squares fit of those
# actions on those states gives the raw W and b (so every a_j, coordinate by coordinate, against the
# encoded parameters beside them), and the public dynamics and reward definition give the raw return
# from the rollout (CartPole: its number of steps). Encoding states and actions with secrets of their
# own would not hold either: public dynamics pin a diagonal state scale (initial-state range,
# termination thresholds, x' = x + tau x_dot). So no privacy mechanism is offered with them.
RAW_EVIDENCE_METHODS = ("r2po",)
PRIVACY_SWITCHES = ("encode_params", "scale_rewards", *HARDENING)


def check_method(method: str, mech: Mechanisms) -> None:
    """Refuse a privacy mechanism for a method whose prompts would undo it (docs/threat-model.md)."""
    if method in RAW_EVIDENCE_METHODS:
        on = [k for k in PRIVACY_SWITCHES if getattr(mech, k)]
        if on:
            flags = ", ".join("--" + k.replace("_", "-") + " on" for k in on)
            raise ConfigError(
                f"--method {method} shows the critic raw states and actions, from which a least-squares fit gives the raw "
                f"policy (hence A) and the rollout gives the raw return, so it cannot run with {flags}; "
                "use --method pp or pp-hardened for a private search"
            )


def resolve(method: str, **overrides: bool | None) -> Mechanisms:
    """A preset, with any mechanism switched on or off individually."""
    if method not in PRESETS:
        raise ConfigError(f"unknown method {method!r}; choose one of {', '.join(PRESETS)}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    unknown = set(changes) - set(Mechanisms.__dataclass_fields__)
    if unknown:
        raise ConfigError(f"unknown mechanism(s): {', '.join(sorted(unknown))}")
    mech = replace(PRESETS[method], **changes)
    mech.check()
    return mech
