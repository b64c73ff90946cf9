"""The linear policy u = W^T s + b and its one flat parameter layout.

Layout of theta (length D = (n_s + 1) * n_a), row-major over W then the bias:

    theta[i * n_a + j]      = W[i, j]   for observation i in [0, n_s), action j in [0, n_a)
    theta[n_s * n_a + j]    = b[j]

So action j's score is  u_j = sum_i s_i * theta[i * n_a + j] + theta[n_s * n_a + j].
Every prompt describes this same layout (see ``ppprops.wire.layout``).

A task may declare another policy family instead (``PolicySpec``): an MLP whose flat theta holds
its layers in order, each layer's weights then its bias, the linear layout being the one-layer
case; ``make_network`` builds the controller of either family.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, model_validator

from .errors import ConfigError

FloatArray = NDArray[np.float64]


def param_count(n_s: int, n_a: int) -> int:
    """D = (n_s + 1) n_a: the weights W (n_s x n_a) and the bias b (n_a) of u = W^T s + b (paper Eq. 10, Sec. III)."""
    return (n_s + 1) * n_a


@dataclass(frozen=True)
class LinearPolicy:
    """A deployable linear controller: continuous actions are clipped, discrete ones take the argmax."""

    W: FloatArray  # shape (n_s, n_a)
    b: FloatArray  # shape (n_a,)
    discrete: bool
    low: FloatArray | None = None  # action bounds for continuous control
    high: FloatArray | None = None

    @classmethod
    def from_flat(
        cls,
        theta: NDArray[np.floating],
        n_s: int,
        n_a: int,
        *,
        discrete: bool,
        low: NDArray[np.floating] | None = None,
        high: NDArray[np.floating] | None = None,
    ) -> LinearPolicy:
        """The policy of a flat theta of shape ((n_s + 1) n_a,) in the module's layout.

        ``low``/``high``: continuous action bounds, shape (n_a,). Raises ConfigError for a theta
        of another length.
        """
        theta64: NDArray[np.float64] = np.asarray(theta, dtype=np.float64)
        if theta64.shape != (param_count(n_s, n_a),):
            raise ConfigError(
                f"policy needs {param_count(n_s, n_a)} parameters for n_s={n_s}, n_a={n_a}, got shape {theta64.shape}"
            )
        W = theta64[: n_s * n_a].reshape(n_s, n_a).copy()
        b = theta64[n_s * n_a :].copy()
        lo = None if low is None else np.asarray(low, dtype=np.float64)
        hi = None if high is None else np.asarray(high, dtype=np.float64)
        return cls(W=W, b=b, discrete=discrete, low=lo, high=hi)

    @property
    def n_s(self) -> int:
        """Length of the state vector s."""
        return int(self.W.shape[0])

    @property
    def n_a(self) -> int:
        """Number of action scores (discrete actions, or continuous action dimensions)."""
        return int(self.W.shape[1])

    def flat(self) -> FloatArray:
        """theta in the one flat layout (module docstring), shape ((n_s + 1) n_a,); inverse of ``from_flat``."""
        return np.concatenate([self.W.reshape(-1), self.b])

    def scores(self, s: NDArray[np.floating]) -> FloatArray:
        """u = W^T s + b for a state ``s`` of shape (n_s,); shape (n_a,)."""
        return np.asarray(s, dtype=np.float64) @ self.W + self.b

    def act(self, s: NDArray[np.floating]) -> int | FloatArray:
        """The action for state ``s`` (shape (n_s,)): argmax of u (discrete), or u clipped to [low, high]."""
        u = self.scores(s)
        if self.discrete:
            return int(np.argmax(u))
        if self.low is not None and self.high is not None:
            return np.clip(u, self.low, self.high)
        return u


# -- policy families ------------------------------------------------------------------------------
Activation = Literal["tanh", "relu"]
ACTIVATIONS: tuple[str, ...] = ("tanh", "relu")
MAX_HIDDEN = 4096  # one hidden layer's width: past it a typo is far likelier than intent
INIT_GAIN = 1.0  # the warm-up draws layer l uniformly on +-INIT_GAIN / sqrt(fan_in_l) (PyTorch's nn.Linear default)
FORWARD_TEXT = ("h_0 = s; h_l = act(h_{l-1} @ W_l + b_l) for each hidden layer l = 1..L-1; "
                "u = h_{L-1} @ W_L + b_L; the action is argmax(u) (discrete) or clip(u, low, high) (continuous)")


class PolicySpec(BaseModel):
    """A policy family as data: ``linear`` (the paper's u = W^T s + b, Eq. 10) or ``mlp`` (hidden
    layers of the given widths, each followed by ``activation``; a linear output layer).

    The flat parameter vector theta (length D = ``param_count``) holds the layers in order, input to
    output; each layer's weights W_l (fan_in x fan_out, row-major: theta[o + i * fan_out + j] =
    W_l[i, j]) come before its bias b_l (fan_out values). The linear policy is the one-layer case,
    so its layout is ``ppprops.policy``'s. Stored in a task declaration (``TaskSpec.policy``) and
    in MLP policy files.

    Raises:
        ValueError: on construction, an ``mlp`` without hidden sizes, a size < 1 or > MAX_HIDDEN,
            a ``linear`` with hidden sizes, an unknown activation (``parse_policy`` words them).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["linear", "mlp"] = "linear"
    hidden: tuple[int, ...] = ()
    activation: Activation = "tanh"

    @model_validator(mode="after")
    def _consistent(self) -> PolicySpec:
        if self.kind == "mlp" and not self.hidden:
            raise ValueError("an mlp policy needs hidden sizes, e.g. mlp:16 or mlp:16,16")
        if self.kind == "linear" and self.hidden:
            raise ValueError("a linear policy has no hidden layers (use mlp:...)")
        bad = [h for h in self.hidden if not 1 <= h <= MAX_HIDDEN]
        if bad:
            raise ValueError(f"hidden sizes must be whole numbers in [1, {MAX_HIDDEN}], got {bad[0]}")
        return self

    @property
    def is_linear(self) -> bool:
        """True for the paper's linear policy (one layer, no activation)."""
        return self.kind == "linear"

    def sizes(self, n_s: int, n_a: int) -> tuple[int, ...]:
        """The widths from input to output: (n_s, *hidden, n_a)."""
        return (n_s, *self.hidden, n_a)

    def layer_shapes(self, n_s: int, n_a: int) -> list[tuple[int, int]]:
        """(fan_in, fan_out) of each layer, input to output: W_l has this shape, b_l has fan_out values."""
        s = self.sizes(n_s, n_a)
        return list(zip(s[:-1], s[1:], strict=True))

    def param_count(self, n_s: int, n_a: int) -> int:
        """D = sum over layers of (fan_in + 1) fan_out; (n_s + 1) n_a for the linear policy (Eq. 10)."""
        return sum((i + 1) * o for i, o in self.layer_shapes(n_s, n_a))

    def layer_slices(self, n_s: int, n_a: int) -> list[tuple[slice, slice]]:
        """(W_l's slice, b_l's slice) of theta for each layer, in the documented order."""
        out, at = [], 0
        for i, o in self.layer_shapes(n_s, n_a):
            out.append((slice(at, at + i * o), slice(at + i * o, at + i * o + o)))
            at += (i + 1) * o
        return out

    def layer_scales(self, n_s: int, n_a: int) -> list[float]:
        """Each layer's share of the run's box: 1 for the linear policy (the paper's box, unchanged);
        1/sqrt(fan_in) for an MLP layer, so every layer's pre-activation spans about the same range."""
        if self.is_linear:
            return [1.0]
        return [1.0 / math.sqrt(i) for i, _ in self.layer_shapes(n_s, n_a)]

    def layer_boxes(self, n_s: int, n_a: int, box: tuple[float, float]) -> list[tuple[float, float]]:
        """(low, high) of every parameter of each layer: the run's ``box`` times ``layer_scales``."""
        lo, hi = box
        return [(lo * g, hi * g) for g in self.layer_scales(n_s, n_a)]

    def bounds(self, n_s: int, n_a: int, box: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
        """The layer boxes per coordinate of theta: (low, high), each of shape (D,)."""
        return self._per_coordinate(n_s, n_a, self.layer_boxes(n_s, n_a, box))

    def init_bounds(self, n_s: int, n_a: int, box: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
        """Where an MLP's warm-up draws each parameter (shape (D,) each): +-INIT_GAIN / sqrt(fan_in)
        of its layer, inside the layer box. The linear policy draws in the whole box (the paper's)."""
        if self.is_linear:
            return self.bounds(n_s, n_a, box)
        boxes = []
        for (lo, hi), (i, _) in zip(self.layer_boxes(n_s, n_a, box), self.layer_shapes(n_s, n_a), strict=True):
            r = INIT_GAIN / math.sqrt(i)
            boxes.append((max(lo, -r), min(hi, r)) if max(lo, -r) < min(hi, r) else (lo, hi))
        return self._per_coordinate(n_s, n_a, boxes)

    def _per_coordinate(self, n_s: int, n_a: int, boxes: list[tuple[float, float]]) -> tuple[FloatArray, FloatArray]:
        D = self.param_count(n_s, n_a)
        lo, hi = np.empty(D), np.empty(D)
        for (w, b), (low, high) in zip(self.layer_slices(n_s, n_a), boxes, strict=True):
            lo[w], hi[w], lo[b], hi[b] = low, high, low, high
        return lo, hi

    def label(self) -> str:
        """The flag's form: ``linear``, ``mlp:16,16 (tanh)``."""
        return "linear" if self.is_linear else f"mlp:{','.join(map(str, self.hidden))} ({self.activation})"

    def to_json(self) -> dict[str, Any]:
        """The stored form (task declarations, policy files)."""
        if self.is_linear:
            return {"kind": "linear"}
        return {"kind": "mlp", "hidden": list(self.hidden), "activation": self.activation}


LINEAR = PolicySpec()


def parse_policy(value: Any, activation: str | None = None) -> PolicySpec:
    """A policy family from any form a user gives one in: ``"linear"``, ``"mlp:16"``,
    ``"mlp:16,16"`` (the ``--policy`` flag), a mapping ``{"kind": "mlp", "hidden": [16],
    "activation": "relu"}`` (Python, a task file's ``[policy]`` table), or a ``PolicySpec``.
    ``activation`` (``--activation``), when given, replaces the activation.

    Raises:
        ValueError: one line naming what is wrong (``mlp:0``, ``mlp:16,x``, an unknown kind or activation).
    """
    if isinstance(value, PolicySpec):
        spec = value
    elif isinstance(value, str):
        kind, _, rest = value.strip().partition(":")
        kind = kind.strip().lower()
        if kind == "linear" and not rest:
            spec = LINEAR
        elif kind == "mlp":
            if not rest.strip():
                raise ValueError(f"policy {value!r}: an mlp needs hidden sizes, e.g. mlp:16 or mlp:16,16")
            sizes = []
            for part in rest.split(","):
                p = part.strip()
                if not p.isdigit() or not 1 <= int(p) <= MAX_HIDDEN:
                    raise ValueError(f"policy {value!r}: hidden sizes must be whole numbers in [1, {MAX_HIDDEN}], got {p!r}")
                sizes.append(int(p))
            spec = PolicySpec(kind="mlp", hidden=tuple(sizes))
        else:
            raise ValueError(f"policy must be linear or mlp:H1[,H2,...] (hidden sizes), got {value!r}")
    elif isinstance(value, Mapping):
        known = {"kind", "hidden", "activation"}
        extra = sorted(set(value) - known)
        if extra:
            raise ValueError(f"policy: unknown key {extra[0]!r} (known: kind, hidden, activation)")
        kind = value.get("kind", "linear")
        if kind not in ("linear", "mlp"):
            raise ValueError(f"policy kind must be linear or mlp, got {kind!r}")
        hidden = value.get("hidden", [])
        if isinstance(hidden, int) and not isinstance(hidden, bool):
            hidden = [hidden]
        if not isinstance(hidden, (list, tuple)) or not all(isinstance(h, int) and not isinstance(h, bool) for h in hidden):
            raise ValueError(f"policy hidden must be a list of whole numbers, got {hidden!r}")
        bad = [h for h in hidden if not 1 <= h <= MAX_HIDDEN]
        if bad:
            raise ValueError(f"policy hidden sizes must be whole numbers in [1, {MAX_HIDDEN}], got {bad[0]}")
        act = value.get("activation", "tanh")
        if act not in ACTIVATIONS:
            raise ValueError(f"policy activation must be one of {', '.join(ACTIVATIONS)}, got {act!r}")
        if kind == "mlp" and not hidden:
            raise ValueError("policy: an mlp needs hidden sizes, e.g. {\"kind\": \"mlp\", \"hidden\": [16]}")
        if kind == "linear" and (hidden or "activation" in value):
            raise ValueError("policy: a linear policy has no hidden layers or activation (use kind \"mlp\")")
        spec = PolicySpec(kind=kind, hidden=tuple(hidden), activation=act)
    else:
        raise ValueError(f"policy must be linear, mlp:H1[,H2,...] or a mapping, got {type(value).__name__}")
    if activation is not None:
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {activation!r}")
        if spec.is_linear:
            raise ValueError("--activation applies to an mlp policy (--policy mlp:...), not to the linear one")
        spec = spec.model_copy(update={"activation": activation})
    return spec


def activate(x: FloatArray, activation: str) -> FloatArray:
    """tanh(x) or relu(x) = max(x, 0), elementwise."""
    return np.tanh(x) if activation == "tanh" else np.maximum(x, 0.0)


@dataclass(frozen=True)
class MLPPolicy:
    """A deployable MLP controller: ``layers`` = ((W_1, b_1), ..., (W_L, b_L)), W_l of shape
    (fan_in, fan_out); the forward pass is ``FORWARD_TEXT``; continuous actions are clipped,
    discrete ones take the argmax."""

    layers: tuple[tuple[FloatArray, FloatArray], ...]
    activation: str
    discrete: bool
    low: FloatArray | None = None
    high: FloatArray | None = None

    @classmethod
    def from_flat(
        cls,
        theta: NDArray[np.floating],
        spec: PolicySpec,
        n_s: int,
        n_a: int,
        *,
        discrete: bool,
        low: NDArray[np.floating] | None = None,
        high: NDArray[np.floating] | None = None,
    ) -> MLPPolicy:
        """The network of a flat theta of shape (D,) in ``PolicySpec``'s order. Raises ConfigError for another length."""
        theta64: NDArray[np.float64] = np.asarray(theta, dtype=np.float64)
        D = spec.param_count(n_s, n_a)
        if theta64.shape != (D,):
            raise ConfigError(f"policy {spec.label()} needs {D} parameters for n_s={n_s}, n_a={n_a}, got shape {theta64.shape}")
        layers = tuple((theta64[w].reshape(i, o).copy(), theta64[b].copy())
                       for (w, b), (i, o) in zip(spec.layer_slices(n_s, n_a), spec.layer_shapes(n_s, n_a), strict=True))  # fmt: skip
        lo = None if low is None else np.asarray(low, dtype=np.float64)
        hi = None if high is None else np.asarray(high, dtype=np.float64)
        return cls(layers=layers, activation=spec.activation, discrete=discrete, low=lo, high=hi)

    @property
    def n_s(self) -> int:
        """Length of the state vector s."""
        return int(self.layers[0][0].shape[0])

    @property
    def n_a(self) -> int:
        """Number of action scores."""
        return int(self.layers[-1][0].shape[1])

    def flat(self) -> FloatArray:
        """theta in the documented order (shape (D,)); inverse of ``from_flat``."""
        return np.concatenate([np.concatenate([W.reshape(-1), b]) for W, b in self.layers])

    def scores(self, s: NDArray[np.floating]) -> FloatArray:
        """u of the forward pass (``FORWARD_TEXT``) for a state of shape (n_s,); shape (n_a,)."""
        h = np.asarray(s, dtype=np.float64)
        for W, b in self.layers[:-1]:
            h = activate(h @ W + b, self.activation)
        W, b = self.layers[-1]
        return h @ W + b

    def act(self, s: NDArray[np.floating]) -> int | FloatArray:
        """The action for state ``s``: argmax of u (discrete), or u clipped to [low, high]."""
        u = self.scores(s)
        if self.discrete:
            return int(np.argmax(u))
        if self.low is not None and self.high is not None:
            return np.clip(u, self.low, self.high)
        return u


def make_network(
    theta: NDArray[np.floating],
    spec: PolicySpec,
    n_s: int,
    n_a: int,
    *,
    discrete: bool,
    low: NDArray[np.floating] | None = None,
    high: NDArray[np.floating] | None = None,
) -> LinearPolicy | MLPPolicy:
    """The controller of theta (shape (D,)) in the family ``spec``: a ``LinearPolicy`` for the linear
    family (the paper's, unchanged), an ``MLPPolicy`` otherwise. Raises ConfigError for a wrong length."""
    if spec.is_linear:
        return LinearPolicy.from_flat(theta, n_s, n_a, discrete=discrete, low=low, high=high)
    return MLPPolicy.from_flat(theta, spec, n_s, n_a, discrete=discrete, low=low, high=high)
