"""Value types the search passes around: one candidate's raw feedback, the recorded candidate, the
final evaluation. Plain frozen data with no behaviour beyond their JSON forms, so proposers, the
loop, the store and the reports share them without importing each other.

Everything here is client-side: it holds raw parameters and raw returns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # the policy module brings pydantic; a stored trial is read without it (``ppprops ask``)
    from .policy import PolicySpec

Diagnostic = float | str  # a diagnostic's value: a number, or a category such as a termination cause


@dataclass(frozen=True)
class Feedback:
    """Raw feedback of one candidate over its episodes (paper, Sec. II-C).

    Attributes:
        ret: mean episode return (raw reward units).
        components: mean of each reward component's per-episode sum, by name.
        diagnostics: numeric diagnostics averaged over the episodes; categorical ones counted
            (``"pole_fell x3, time_limit x1"``).
        episode_returns: each episode's return, in seed order.
    """

    ret: float
    components: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, Diagnostic] = field(default_factory=dict)
    episode_returns: tuple[float, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """The stored form (``return``, ``components``, ``diagnostics``, ``episode_returns``)."""
        return {
            "return": self.ret,
            "components": self.components,
            "diagnostics": self.diagnostics,
            "episode_returns": list(self.episode_returns),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Feedback:
        """The inverse of ``to_json``; ``episode_returns`` may be absent (older stores)."""
        return cls(
            ret=float(d["return"]),
            components={k: float(v) for k, v in d["components"].items()},
            diagnostics=dict(d["diagnostics"]),
            episode_returns=tuple(float(v) for v in d.get("episode_returns", ())),
        )


@dataclass(frozen=True)
class Candidate:
    """One evaluated policy as the store records it, raw and encoded (client-side only).

    Attributes:
        index: position in the run, from 0 (warm-up first); unique per run.
        iteration: the proposer's own ask number (warm-up sample, or LLM iteration).
        source: who proposed it: ``warmup``, ``llm``, ``fallback``, ``random``, ``cmaes``, ...
        params: raw theta, shape (D,), decoded and clipped into the box.
        params_enc: the encoded theta~ = A theta (Eq. 5; hardened: A (T(theta) - T(m))), shape (D,).
        feedback: raw feedback.
        feedback_enc: feedback with returns and components scaled (Eq. 7-8); diagnostics as they are.
        clipped: coordinates that had to be clipped into the box.
        seeds: the episode seeds it was evaluated on.
        note: why a fallback was used, or other remarks.
        ask_s: seconds in the proposer's ask (LLM calls included); None when not measured.
        eval_s: seconds evaluating its episodes; None when not measured.
        reevaluates: for a re-evaluation of the selection stage (source ``reeval``), the index of
            the search candidate it re-evaluates on fresh episodes; None otherwise.
    """

    index: int
    iteration: int
    source: str
    params: np.ndarray
    params_enc: np.ndarray
    feedback: Feedback
    feedback_enc: Feedback
    clipped: int
    seeds: tuple[int, ...]
    note: str = ""
    ask_s: float | None = None
    eval_s: float | None = None
    reevaluates: int | None = None

    @property
    def ret(self) -> float:
        """The raw mean return (``feedback.ret``)."""
        return self.feedback.ret


@dataclass(frozen=True)
class FinalEval:
    """The final evaluation: the best candidate run on fresh episode seeds (``seeding.final_eval_seeds``)."""

    candidate_index: int
    returns: tuple[float, ...]
    seeds: tuple[int, ...]

    @property
    def mean(self) -> float:
        """Mean return; NaN with no episodes, inf when an episode overflowed."""
        with np.errstate(invalid="ignore", over="ignore"):  # an episode that overflowed makes this inf, quietly
            return float(np.mean(self.returns)) if self.returns else float("nan")

    @property
    def std(self) -> float:
        """Standard deviation of the returns (population); NaN with no episodes."""
        with np.errstate(invalid="ignore", over="ignore"):
            return float(np.std(self.returns)) if self.returns else float("nan")


@dataclass(frozen=True, eq=False)
class Trial:
    """A candidate the study asks to be evaluated (``Study.ask``), before its feedback is told.

    Attributes:
        number: its index in the run, from 0 (warm-up first); the candidate it becomes has it.
        phase: the phase that asked it: ``warmup``, ``llm``, ``r2po``, ``random``, ``cmaes``, ...
        iteration: the proposer's own ask number within the phase.
        source: who proposed it: ``warmup``, ``llm``, ``fallback``, ``random``, ``cmaes``, ...
        theta: the raw parameters to run, shape (D,), inside the box: D = (n_s + 1) n_a for the
            linear policy; an MLP's layers in order, each layer's weights then its bias (``ppprops.policy``).
        n_s, n_a: the policy's state and action sizes (``W`` and ``b``, or ``layers``, come from ``theta``).
        policy: the policy family (``ppprops.policy.PolicySpec``); None: the paper's linear policy.
        seeds: the episode seeds to reset a simulator with, one per episode asked for; a robot
            that cannot be seeded ignores them (its episodes' initial states are its own).
        clipped: coordinates that had to be clipped into the box.
        note: why a fallback was used, or other remarks.
        ask_s: seconds the proposer took to ask it (LLM calls included).
        reevaluates: a re-evaluation of the selection stage: the search candidate it runs again.
        worker: the worker holding it (``Study.ask(worker=...)``, ``ppprops ask --worker``): ""
            for a trial asked without a worker name, None for one nobody holds yet.
    """

    number: int
    phase: str
    iteration: int
    source: str
    theta: np.ndarray
    n_s: int
    n_a: int
    seeds: tuple[int, ...]
    clipped: int = 0
    note: str = ""
    ask_s: float | None = None
    reevaluates: int | None = None
    worker: str | None = None
    policy: PolicySpec | None = None

    @property
    def is_linear(self) -> bool:
        """True for the paper's linear policy u = W^T s + b (``policy`` None or linear)."""
        return self.policy is None or self.policy.is_linear

    def _family(self) -> PolicySpec:
        from .policy import LINEAR

        return LINEAR if self.policy is None else self.policy

    @property
    def W(self) -> np.ndarray:
        """The weights of u = W^T s + b (paper Eq. 10), shape (n_s, n_a) (layout: ``ppprops.policy``).

        Raises:
            AttributeError: an MLP trial (it has ``layers``).
        """
        self._linear("W")
        return np.asarray(self.theta[: self.n_s * self.n_a], dtype=np.float64).reshape(self.n_s, self.n_a)

    @property
    def b(self) -> np.ndarray:
        """The bias of u = W^T s + b, shape (n_a,). Raises AttributeError for an MLP trial (``layers``)."""
        self._linear("b")
        return np.asarray(self.theta[self.n_s * self.n_a:], dtype=np.float64)

    def _linear(self, name: str) -> None:
        if not self.is_linear:
            raise AttributeError(f"trial {self.number} is an {self._family().label()} policy: it has layers ((W_l, b_l) pairs), not one {name}")

    @property
    def layers(self) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """(W_l, b_l) of each layer, input to output: W_l of shape (fan_in, fan_out), b_l of shape (fan_out,).
        One pair, (W, b), for the linear policy. The forward pass: ``ppprops.policy.FORWARD_TEXT``."""
        theta = np.asarray(self.theta, dtype=np.float64)
        return tuple((theta[w].reshape(i, o), theta[b]) for (w, b), (i, o)
                     in zip(self._family().layer_slices(self.n_s, self.n_a), self._family().layer_shapes(self.n_s, self.n_a), strict=True))  # fmt: skip

    @property
    def episodes(self) -> int:
        """Episodes asked for (their mean is the candidate's return)."""
        return len(self.seeds)

    def to_json(self) -> dict[str, Any]:
        """What ``ppprops ask`` prints: every field, ``theta`` flat and as ``W`` (rows of n_a) and ``b``;
        an MLP trial gives ``layers`` (each ``{"W": rows, "b": values}``), its ``policy`` and the ``forward`` pass instead."""
        shape: dict[str, Any]
        if self.is_linear:
            shape = {"W": [[float(v) for v in row] for row in self.W], "b": [float(v) for v in self.b]}
        else:
            from .policy import FORWARD_TEXT

            shape = {"policy": self._family().to_json(), "forward": FORWARD_TEXT,
                     "layers": [{"W": W.tolist(), "b": b.tolist()} for W, b in self.layers]}
        return {
            "trial": self.number,
            "phase": self.phase,
            "iteration": self.iteration,
            "source": self.source,
            "theta": [float(v) for v in self.theta],
            **shape,
            "n_s": self.n_s,
            "n_a": self.n_a,
            "episodes": self.episodes,
            "seeds": list(self.seeds),
            "clipped": self.clipped,
            "note": self.note,
            "reevaluates": self.reevaluates,
            **({"worker": self.worker} if self.worker else {}),
        }

    def __eq__(self, other: object) -> bool:
        """Equal when every field is (``theta`` value by value)."""
        if not isinstance(other, Trial):
            return NotImplemented
        mine, theirs = dict(self.__dict__), dict(other.__dict__)
        return np.array_equal(mine.pop("theta"), theirs.pop("theta")) and mine == theirs

    __hash__ = None  # type: ignore[assignment]  # holds an array: not hashable

    def __repr__(self) -> str:
        """One line: the number, where it came from, its size; not the raw parameters."""
        return f"Trial(number={self.number}, phase={self.phase!r}, source={self.source!r}, D={len(self.theta)}, episodes={self.episodes})"
