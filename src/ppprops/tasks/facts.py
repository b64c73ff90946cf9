"""A task's privacy facts: what a curious provider may know about it without any secret.

One model, ``PrivacyFacts``, holds them everywhere: a task file's ``[privacy]`` table validates
into it (``tasks.schema.TaskFile.privacy``), the task's ``TaskSpec`` stores it with every run, and
the codec (``client.hardening``) and the attacks (``ppprops.privacy``) read it, completed for the
task by ``ppprops.privacy.knowledge.facts_for``. Each fact is either declared or unknown
(``None``); ``False`` in a name, formula, range or time-limit fact states that the task has none,
which is known. The stored form holds the declared facts only.

Completed facts (``PrivacyFacts.completed``) are what the readers use and are never stored: an
unknown fact takes its neutral value (False, empty, None), the facts pp-hardened needs a value for
take their fallback (``public_env`` from the env, ``residual_component``, ``reward_scale``,
``return_determining`` always with ``episode_length``), and ``unknown`` still names every fact the
task left undeclared, so an attack that needs one says why it did not run (``not_run``).

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

from collections.abc import Sequence
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, SerializerFunctionWrapHandler, StringConstraints, model_serializer, model_validator

Text = Annotated[str, StringConstraints(strip_whitespace=True, min_length=1)]
Number = Annotated[float, Field(allow_inf_nan=False)]
Name = Literal[False]  # `false` in a name-valued fact: the task has no such thing (known, not unknown)

ALWAYS_HIDDEN = ("episode_length",)  # pp-hardened hides it for every task (it states the time limit)
DEFAULT_REWARD_SCALE = 1000.0  # the bound of the secret offsets when a task states no scale (then listed as unknown)

# As a task file's tables: strict types, no unknown key; built on first use, not at import.
TABLE = ConfigDict(extra="forbid", strict=True, frozen=True, defer_build=True)


class Cap(BaseModel):
    """A return that a marked episode end pins: ``{ side = "max", value = 500.0, diagnostic = "termination", marker = "time_limit" }``."""

    model_config = TABLE

    side: Literal["max", "min"] = Field(description="max or min")
    value: Number = Field(description="a number (the pinned return)")
    diagnostic: Text = Field(description="a diagnostic name")
    marker: Text = Field(description="a string (the diagnostic's value that marks the cap)")


class PrivacyFacts(BaseModel):
    """A task's privacy facts: its ``[privacy]`` table, stored with its declaration (see the module docstring).

    Every key may be left out: the fact is then unknown (``None``), and the audit says which
    attacks it could not run because of that. ``false`` for a name, a formula, a range or a time
    limit states that the task has none (a known fact). Each field's ``description`` is what a
    value of it must be (the task file's error lines are written from it).
    """

    model_config = TABLE

    public_env: bool | None = Field(default=None, description="true or false")
    integer_returns: bool | None = Field(default=None, description="true or false")
    return_formula: dict[str, Number] | Name | None = Field(
        default=None, description="a table of diagnostic = coefficient (raw return = sum of coefficient x diagnostic + constant), or false")
    return_formula_constant: Number | None = Field(default=None, description="a number")
    caps: list[Cap] | None = Field(default=None, description="a list of { side, value, diagnostic, marker } tables")
    return_range: Annotated[list[Number], Field(min_length=2, max_length=2)] | Name | None = Field(
        default=None, description="[low, high] (one episode's return), or false when unbounded")
    resolution: dict[str, Annotated[float, Field(gt=0, allow_inf_nan=False)]] | None = Field(
        default=None, description="a table of quantity = step > 0 (quantity: return or a component)")
    survive_component: Text | Name | None = Field(default=None, description="a component name, or false")
    healthy_reward: Number | None = Field(default=None, description="a number (reward units per step)")
    ctrl_component: Text | Name | None = Field(default=None, description="a component name, or false")
    ctrl_per_step: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = Field(default=None, description="a number >= 0")
    time_limit: Annotated[int, Field(ge=1)] | Name | None = Field(default=None, description="a positive integer (steps), or false")
    components_sum_to_return: bool | None = Field(default=None, description="true or false")
    return_determining: list[Text] | None = Field(default=None, description="a list of diagnostic names")
    residual_component: Text | Name | None = Field(default=None, description="a component name, or false")
    reward_scale: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = Field(default=None, description="a number > 0 (reward units)")

    # Set by ``completed`` only: the task the facts are completed for, its components, its unknown facts.
    _task: str = PrivateAttr(default="")
    _components: tuple[str, ...] = PrivateAttr(default=())
    _unknown: tuple[str, ...] | None = PrivateAttr(default=None)

    @model_validator(mode="after")
    def _consistent(self) -> PrivacyFacts:
        if self.return_formula_constant is not None and not self.return_formula:
            raise ValueError("privacy.return_formula_constant needs privacy.return_formula")
        if self.healthy_reward is not None and not self.survive_component:
            raise ValueError("privacy.healthy_reward needs privacy.survive_component")
        if self.ctrl_per_step is not None and not self.ctrl_component:
            raise ValueError("privacy.ctrl_per_step needs privacy.ctrl_component")
        if self.return_range and self.return_range[0] > self.return_range[1]:
            raise ValueError(f"privacy.return_range must be [low, high] with low <= high, got {self.return_range!r}")
        return self

    @model_serializer(mode="wrap")
    def _declared_only(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """The stored form: the declared facts (an unknown one, None, is left out)."""
        return {k: v for k, v in handler(self).items() if v is not None}

    def is_empty(self) -> bool:
        """True when nothing is declared."""
        return all(getattr(self, name) is None for name in FACT_NAMES)

    @property
    def unknown(self) -> tuple[str, ...]:
        """The facts the task leaves undeclared, in ``FACT_NAMES`` order.

        A fact that only refines another is counted only where that other one makes it matter:
        ``healthy_reward`` when ``survive_component`` names a component, ``ctrl_per_step`` when
        ``ctrl_component`` does; ``return_formula_constant`` (0 by default) and ``public_env``
        (``TaskSpec.public_env`` decides it when not declared) never. Completed facts keep the list
        of the declaration they were completed from, less what the task itself states (``completed``).
        """
        if self._unknown is not None:
            return self._unknown
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

    @property
    def task(self) -> str:
        """The name of the task the facts are completed for ("" before ``completed``)."""
        return self._task

    @property
    def components(self) -> tuple[str, ...]:
        """Completed facts: every reward component of the task when they add up to the return, else ()."""
        return self._components

    def missing(self, *facts: str) -> tuple[str, ...]:
        """Those of ``facts`` (names from ``FACT_NAMES``) that the task leaves unknown."""
        return tuple(f for f in facts if f in self.unknown)

    def not_run(self, attack: str, *facts: str) -> str | None:
        """The line the audit prints when ``attack`` needs a fact the task leaves unknown, else None.

        ``attack X not run: fact Y unknown for task Z`` (every unknown fact named, comma-separated),
        e.g. ``facts.not_run("survive-length", "survive_component", "time_limit")``.
        """
        gone = self.missing(*facts)
        if not gone:
            return None
        return f"attack {attack} not run: fact{'s' if len(gone) > 1 else ''} {', '.join(gone)} unknown for task {self.task}"

    def completed(self, task: str, components: Sequence[str], *, optimal_return: float | None, public_env: bool,
                  unknown: Sequence[str] | None = None) -> PrivacyFacts:  # fmt: skip
        """These declared facts completed for a task (what the codec and the attacks read; never stored).

        ``task`` is the task's name and ``components`` its reward components; ``public_env`` is
        ``TaskSpec.public_env()``. An unknown fact takes its neutral value (False, empty, None; a
        declared ``false`` the same) and stays in ``unknown``, except where pp-hardened needs a
        value: ``return_determining`` always holds ``episode_length``, ``residual_component``
        falls back to the first component (one must be left out to close the additivity attack),
        and ``reward_scale`` to |optimal return|, else ``DEFAULT_REWARD_SCALE``. Those fallbacks
        stay listed as unknown, but for a scale that |optimal return| states and a residual of a
        task without components. ``unknown`` replaces the list.
        """
        residual = self.residual_component if self.residual_component is not None else (components[0] if components else False)
        if self.reward_scale is not None:
            scale = float(self.reward_scale)
        elif optimal_return is not None and optimal_return != 0:
            scale = abs(float(optimal_return))
        else:
            scale = DEFAULT_REWARD_SCALE
        if unknown is None:
            unknown = [f for f in self.unknown if not (f == "reward_scale" and optimal_return)  # |optimal return| states it
                       and not (f == "residual_component" and not components)]  # fmt: skip
        out = self.model_copy(update={
            "public_env": public_env,
            "integer_returns": bool(self.integer_returns),
            "return_formula": dict(self.return_formula) if self.return_formula else {},
            "return_formula_constant": float(self.return_formula_constant or 0.0),
            "caps": list(self.caps or ()),
            "return_range": self.return_range or None,
            "resolution": dict(self.resolution or {}),
            "survive_component": self.survive_component or None,
            "ctrl_component": self.ctrl_component or None,
            "time_limit": self.time_limit or None,
            "components_sum_to_return": bool(self.components_sum_to_return),
            "return_determining": list(dict.fromkeys((*ALWAYS_HIDDEN, *(self.return_determining or ())))),
            "residual_component": residual or None,
            "reward_scale": scale,
        })  # fmt: skip
        out._task = task
        out._components = tuple(components) if self.components_sum_to_return else ()
        out._unknown = tuple(unknown)
        return out


# The facts in the order the docs list them; ``return_formula_constant`` belongs to ``return_formula``.
FACT_NAMES: tuple[str, ...] = tuple(PrivacyFacts.model_fields)

__all__ = ["ALWAYS_HIDDEN", "DEFAULT_REWARD_SCALE", "FACT_NAMES", "Cap", "PrivacyFacts"]
