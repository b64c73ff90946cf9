"""Value types that are safe to show the provider: already-encoded numbers and public prose."""

from __future__ import annotations

from dataclasses import dataclass

from .numbers import NumberFormat, number_format


@dataclass(frozen=True)
class EncodedEntry:
    """One history entry as the LLM may see it.

    ``params`` are theta~ = A theta (or theta itself when the preset does not encode parameters);
    ``ret`` and ``components`` are c * r (or r when rewards are not scaled); ``diagnostics`` are
    non-reward quantities and are shown as they are. ``index`` orders ties stably and is never shown.
    """

    index: int
    params: tuple[float, ...]
    ret: float
    components: tuple[tuple[str, float], ...] = ()
    diagnostics: tuple[tuple[str, float | str], ...] = ()


@dataclass(frozen=True)
class PromptContext:
    """Public facts about the task and the preset, fixed for a run. Built once by the client."""

    summary: str
    observations: tuple[tuple[str, str], ...]  # (name, meaning) per state variable, in layout order
    actions: tuple[str, ...]
    discrete: bool
    reward_text: str
    hints: str
    encoded_params: bool
    scaled_rewards: bool
    detailed_feedback: bool
    param_range: tuple[float, float] | None  # shown only for unencoded parameters
    optimum: float | None  # already on the prompt's reward scale; None when withheld
    component_notes: tuple[tuple[str, str], ...] = ()
    diagnostic_notes: tuple[tuple[str, str], ...] = ()
    decimals: int = 2
    history_limit: int = 0  # K, 0 for unbounded; only shapes the wording
    # How the encoding is described (docs/threat-model.md): "scale" is the paper's wording;
    # "affine" adds secret offsets; "warp" is an undisclosed increasing map. Only the words change.
    param_encoding: str = "scale"
    reward_encoding: str = "scale"
    warmup_range: tuple[float, float] | None = None  # public encoded range of the warm-up (hardened)
    # Prompt form, not meaning (benchmarks/RESULTS.md measured both choices):
    # "list" writes a history entry's parameters as one JSON-like list, "indexed" as the
    # ProPS-style ``params[i]: value`` pairs; "static-first" puts every fixed section before the
    # history so a server's prefix cache reuses them, "history-first" is the opposite order.
    params_style: str = "list"
    param_digits: int = 3  # list form: significant digits of a parameter (at most ``decimals`` decimals); 0: fixed decimals
    layout: str = "static-first"
    title: str = ""  # the task's name, the document form's header (wire.document)
    # ProPS+ (True): the task section describes the environment, the state and action meanings,
    # the reward text and hints. ProPS (False): it says only how the policy maps states to actions.
    describe_task: bool = True
    # The policy's structure (public): the hidden layers' widths of an MLP (() for the paper's linear
    # policy), their activation, and, shown only for unencoded parameters, each layer's (low, high).
    hidden: tuple[int, ...] = ()
    activation: str = ""
    layer_ranges: tuple[tuple[float, float], ...] | None = None

    # How encoded parameters are written (wire.numbers.NUMBER_FORMATS): "grid", integers on the client's
    # secret grid, or "decimal", significant digits (every run stored before the grid existed).
    number_format: str = "decimal"

    @property
    def numbers(self) -> NumberFormat:
        """The number format of the parameters (``wire.numbers.number_format``; ValueError for an unknown name)."""
        return number_format(self.number_format)

    @property
    def param_decimals(self) -> int:
        """Decimals of a printed parameter in this context's number format."""
        return self.numbers.decimals(self.decimals)

    @property
    def param_sig_digits(self) -> int:
        """Significant digits of a printed parameter in this context's number format (0: fixed decimals)."""
        return self.numbers.digits(self.param_digits)

    @property
    def n_s(self) -> int:
        """Length of the state vector s."""
        return len(self.observations)

    @property
    def n_a(self) -> int:
        """Number of policy outputs (action scores or continuous action dimensions)."""
        return len(self.actions)

    @property
    def sizes(self) -> tuple[int, ...]:
        """The layer widths from input to output: (n_s, *hidden, n_a)."""
        return (self.n_s, *self.hidden, self.n_a)

    @property
    def D(self) -> int:
        """The number of parameters asked for: (n_s + 1) n_a for the linear policy, the sum of the
        layers' (fan_in + 1) fan_out for an MLP (``ppprops.policy.PolicySpec``'s order)."""
        s = self.sizes
        return sum((i + 1) * o for i, o in zip(s[:-1], s[1:], strict=True))
