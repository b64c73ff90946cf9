"""The privacy and feedback mechanisms of the paper (Sec. II), and the presets that combine them.

Each switch of ``Mechanisms`` is one mechanism; the paper's four configurations (vanilla, pe, df,
pp) are named combinations of them (``PRESETS``), and ``pp-hardened`` adds the hardening switches
of docs/threat-model.md. Plain data: the codec (``client.codec``), the prompt context
(``client.context``) and the method registry (``ppprops.methods``) read it.
"""

from __future__ import annotations

from dataclasses import MISSING, asdict, dataclass, fields
from typing import Any

from ..errors import ConfigError


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
    # ProPS+ (on) or ProPS (off): the task description (environment, state and action meanings,
    # reward text, hints) in the prompt. Off leaves the policy structure, feedback, interaction, history.
    describe_task: bool = True
    # Hardening, added later (stored configs without it read it off): drop the diagnostics whose
    # value marks an episode end at a public cap, which pins that entry's raw return exactly
    # (CartPole termination=time_limit: 500; Acrobot success=0: -500).
    hide_anchors: bool = False
    # Transport, not encoding: each new LLM request waits until the gap since the last answer
    # reaches a padded, keyed length, so the provider's clock does not follow evaluation time
    # (llm.pacing; docs/threat-model.md, "The provider's clock"). Costs wall time; off by default.
    pace_requests: bool = False

    def to_json(self) -> dict[str, bool]:
        """Each switch by name, as stored in a run's config."""
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Mechanisms:
        """Reads stored configs, including those written before a switch with a default existed
        (the hardening switches: off; ``describe_task``: on, as every earlier run described its task)."""
        values: dict[str, bool] = {}
        for f in fields(cls):
            if f.name in d:
                values[f.name] = bool(d[f.name])
            elif f.default is not MISSING:
                values[f.name] = bool(f.default)
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


HARDENING = ("secret_offsets", "warp_params", "warp_rewards", "hide_return_diagnostics", "encoded_warmup", "hide_anchors")

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
    "pp-hardened": Mechanisms(True, True, True, False, False, True, True, True, True, True, hide_anchors=True),
}


# Every switch, in declaration order; each is a `--<name with dashes> on|off` flag of `ppprops run`.
SWITCHES: tuple[str, ...] = tuple(f.name for f in fields(Mechanisms))


# The help text of each switch's `--<name> on|off` flag.
SWITCH_HELP: dict[str, str] = {
    "encode_params": "parameters shown as A theta (Sec. II-B)",
    "scale_rewards": "returns and reward components shown as c r (Sec. II-C)",
    "detailed_feedback": "reward components and diagnostics in the history",
    "disclose_optimum": "state the optimal return as a target (Vanilla ProPS)",
    "disclose_reward_structure": "state the numeric reward definition",
    "describe_task": "task description in the prompt: on = ProPS+, off = ProPS (policy structure only)",
    "secret_offsets": "hardening: secret raw origins, A (theta - m) and c (r - s)",
    "warp_params": "hardening: the box mapped onto the real line before A",
    "warp_rewards": "hardening: a secret increasing power warp of the rewards",
    "hide_return_diagnostics": "hardening: drop diagnostics that pin the return",
    "encoded_warmup": "hardening: warm-up drawn in the encoded space",
    "hide_anchors": "hardening: drop diagnostics that mark a return at a public cap (termination=time_limit)",
    "pace_requests": "hardening: pad the gap before each LLM request, so request times do not follow evaluation time (costs wall time)",
}


def switch_flag(name: str) -> str:
    """The command-line flag of a mechanism switch: ``encode_params`` -> ``--encode-params``."""
    return "--" + name.replace("_", "-")


# Switches that hide something from the provider. A method whose prompts show raw trajectory
# evidence (R2PO's critic reads raw states and the actions the policy took in them) refuses them:
# for a linear policy u = W^T s + b a least-squares fit of those actions on those states gives the
# raw W and b (so every a_j, coordinate by coordinate, against the encoded parameters beside them),
# and the public dynamics and reward definition give the raw return from the rollout (CartPole: its
# number of steps). Encoding states and actions with secrets of their own would not hold either:
# public dynamics pin a diagonal state scale (initial-state range, termination thresholds,
# x' = x + tau x_dot). See docs/threat-model.md.
PRIVACY_SWITCHES = ("encode_params", "scale_rewards", *HARDENING)
