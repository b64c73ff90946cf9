"""Every method ppprops runs, in one registry, and the mechanisms the prompted ones combine.

The paper's four configurations (vanilla, pe, df, pp) are combinations of independent
privacy/feedback mechanisms (``Mechanisms``); ``pp-hardened`` adds six switches that close the
side channels measured in docs/threat-model.md (the four paper presets keep every new switch off,
so they behave exactly as the paper defines them). ``describe_task`` is the ProPS / ProPS+
distinction: off, the prompt carries no task description, only the policy structure.

``METHODS`` is the one place that knows each method (``Method``): its kind (a prompted search, a
black-box optimizer at the same budget, or an RL baseline), its mechanisms, its defaults, which
settings it refuses, and how its search phase is built (a builder in ``ppprops.strategies``, or
any callable). The CLI, the experiment specs, the runner and the reports ask it instead of keeping
lists of their own. Adding a method is one ``Method`` entry here (or ``register_method`` from
outside), plus, for a search, one phase builder. ``register_method`` changes this process's
registry only; an installed package makes its methods known to every process (a CLI in a shell,
``ppprops show``, a grid's runs) through the ``ppprops.plugins`` entry points, loaded the first
time a name is not found here (``ppprops.plugins``). docs/architecture.md has the recipe.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator, Mapping
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError

from .client.mechanisms import HARDENING, PRESETS, PRIVACY_SWITCHES, SWITCH_HELP, SWITCHES, Mechanisms, switch_flag
from .errors import ConfigError
from .plugins import load_plugins
from .schema import describe_error
from .wire.names import CHAT_FORM, CHOOSABLE  # names only: the forms (wire.forms) load with the prompts

if TYPE_CHECKING:
    from .baselines.algorithms import Algorithm
    from .proposers.base import Phase, SearchSetup

__all__ = ["HARDENING", "PRESETS", "PRIVACY_SWITCHES", "SWITCH_HELP", "SWITCHES", "Mechanisms", "switch_flag"]


def check_method(method: str, mech: Mechanisms) -> None:
    """Refuse mechanisms ``method`` cannot run with (``Method.check_mechanisms``), as one ConfigError line."""
    get_method(method).check_mechanisms(mech)


def resolve(method: str, **overrides: bool | None) -> Mechanisms:
    """The mechanisms of a search method (a preset, R2PO's, or a black-box method's), with any
    switch turned on or off individually: ``get_method(method).mechanisms(**overrides)``.

    ``overrides`` maps switch names to True/False; None leaves the method's value. Raises
    ConfigError for an unknown method or switch, or a combination the method refuses.
    """
    return get_method(method).mechanisms(**overrides)


def _changes(overrides: dict[str, bool | None]) -> dict[str, bool]:
    changes = {k: bool(v) for k, v in overrides.items() if v is not None}
    unknown = set(changes) - set(SWITCHES)
    if unknown:
        raise ConfigError(f"unknown mechanism(s): {', '.join(sorted(unknown))}")
    return changes


# -- the registry of methods -------------------------------------------------------------------
class MethodKind(StrEnum):
    """How a method finds its policy."""

    PROMPTED = "prompted"  # an LLM proposes candidates from a prompt (the ProPS presets, R2PO)
    BLACK_BOX = "black-box"  # a classical optimizer at the same evaluation budget (random search, CMA-ES)
    RL = "rl"  # a Stable-Baselines3 agent trained on the task (`ppprops baseline rl`)


@dataclass(frozen=True)
class Method:
    """One method: what it is, how it is configured, and how its search phase is built.

    ``name`` is the ``--method`` value and what a run stores as its method (RL baselines:
    ``rl-<algo>``). ``preset`` is the mechanisms a prompted method starts from. A search runs
    ``warmup`` uniform samples, then ``iterations`` asks of the phase its builder returns:
    ``phase`` is the name of a builder in ``ppprops.strategies`` or a callable
    ``(proposers.base.SearchSetup) -> proposers.base.Phase``; ``iterations`` counts what
    ``iteration_unit`` says. ``options`` is the pydantic model of the method's own options (the
    run's ``method_options``, e.g. CMA-ES's population size; None: the method takes none); its
    builder reads them as ``setup.options``. ``forms`` are the ``--prompt-form`` values it takes.
    """

    name: str
    kind: MethodKind
    title: str
    preset: Mechanisms | None = None
    default_episodes: int = 1  # episodes per candidate when --episodes is not given
    iteration_unit: str = "LLM iterations"
    phase: str | Callable[[SearchSetup], Phase] | None = None  # builder (name in ppprops.strategies or callable); None: RL
    top_k_prompt: bool = False  # one LLM call per iteration over a top-K history (history-cost figures)
    raw_evidence: bool = False  # its prompts show raw states and actions: no privacy switch applies (PRIVACY_SWITCHES)
    algo: str | None = None  # RL baselines: the `ppprops baseline rl --algo` value
    options: type[BaseModel] | None = None  # the method's own options (a pydantic model), None: none
    forms: tuple[str, ...] = ("auto", *CHOOSABLE)  # the --prompt-form values it takes
    parallel: bool = True  # takes --parallel P > 1 (its proposer asks P candidates per round); False: one at a time

    @property
    def algorithm(self) -> Algorithm:
        """An RL baseline's library class and the action spaces it takes."""
        from .baselines.algorithms import ALGORITHMS

        if self.algo is None:
            raise ConfigError(f"{self.name} is not an RL baseline")
        return ALGORITHMS[self.algo]

    @property
    def is_search(self) -> bool:
        """Run by `ppprops run` (warm-up and a search phase), not trained by `ppprops baseline rl`."""
        return self.kind is not MethodKind.RL

    @property
    def uses_llm(self) -> bool:
        """True for prompted methods: the run starts (or connects to) an LLM endpoint."""
        return self.kind is MethodKind.PROMPTED

    def mechanisms(self, **overrides: bool | None) -> Mechanisms:
        """The run's mechanisms: the preset with ``overrides`` (switch name -> on/off, None = keep).

        A black-box method sends no prompt: only ``encode_params`` applies (it picks the space
        the optimizer searches) and any other switch given is refused. RL baselines have none.
        Raises ConfigError with the flag to change.
        """
        changes = _changes(overrides)
        if self.kind is MethodKind.RL:
            raise ConfigError(f"{self.name} is an RL baseline: train it with 'ppprops baseline rl --algo {self.algo}'")
        if self.kind is MethodKind.BLACK_BOX:
            other = sorted(k for k in changes if k != "encode_params")
            if other:
                flags = ", ".join(switch_flag(k) for k in other)
                raise ConfigError(f"{flags} does not apply to --method {self.name}: it sends no prompt "
                                  "(only --encode-params does, choosing the space it searches)")  # fmt: skip
            enc = changes.get("encode_params", False)
            return Mechanisms(enc, enc, False, False, False)
        assert self.preset is not None
        mech = replace(self.preset, **changes)
        mech.check()
        return mech

    def check_settings(self, mechanisms: Mechanisms, *, prompt_form: str = "auto", options: Mapping[str, Any] | None = None) -> None:
        """Settings this method refuses, each as one ConfigError line (``RunConfig`` calls it on
        construction): an RL baseline as a search, mechanisms it cannot run with, a prompt form it
        does not use, options it does not know or of the wrong type."""
        if self.kind is MethodKind.RL:
            raise ConfigError(f"{self.name} is an RL baseline: train it with 'ppprops baseline rl --algo {self.algo}'")
        self.check_mechanisms(mechanisms)
        if prompt_form not in self.forms:
            raise ConfigError(f"--prompt-form {prompt_form} does not apply to {self.name}; use {' or '.join(self.forms)}")
        self.parse_options(options)

    def parse_options(self, options: Mapping[str, Any] | None) -> BaseModel | None:
        """The method's own options, validated (``options``: the run's ``method_options``).

        Returns the options model (defaults filled in), or None for a method that takes none.
        Raises ConfigError naming the option for an unknown option or a bad value.
        """
        given = dict(options or {})
        if self.options is None:
            if given:
                raise ConfigError(f"--method-options: {self.name} takes no options, got {', '.join(sorted(given))}")
            return None
        try:
            return self.options(**given)
        except ValidationError as e:
            err = e.errors()[0]
            name = ".".join(str(p) for p in err["loc"]) or "method_options"
            if err["type"] == "extra_forbidden":
                known = ", ".join(self.options.model_fields)
                raise ConfigError(f"--method-options: {self.name} has no option {name!r} (known: {known})") from None
            raise ConfigError(f"--method-options: {describe_error(err, name, None)}") from None

    def check_mechanisms(self, m: Mechanisms) -> None:
        """Mechanisms this method cannot run with, each as one ConfigError line: a combination that
        reveals what it hides, prompt switches for a black box, privacy switches for a method whose
        prompts show raw evidence (``raw_evidence``)."""
        m.check()
        if self.kind is MethodKind.BLACK_BOX:
            if m.detailed_feedback or m.disclose_optimum or m.disclose_reward_structure or m.hardened:
                raise ConfigError(f"--method {self.name} sends no prompt: only --encode-params applies to it")
        if self.raw_evidence:
            on = [k for k in PRIVACY_SWITCHES if getattr(m, k)]
            if on:
                flags = ", ".join(switch_flag(k) + " on" for k in on)
                raise ConfigError(
                    f"--method {self.name} shows the critic raw states and actions, from which a least-squares fit gives the raw "
                    f"policy (hence A) and the rollout gives the raw return, so it cannot run with {flags}; "
                    "use --method pp or pp-hardened for a private search"
                )



class CMAESOptions(BaseModel):
    """``--method-options`` of ``cmaes`` (pycma's own names): ``popsize`` (None: pycma's default,
    4 + 3 ln D) and ``sigma0``, the initial step as a share of the box width in the raw space (in
    the encoded space the step is 1 per coordinate scaled by the warm-up's spread, times
    ``sigma0 / 0.3``)."""

    model_config = ConfigDict(extra="forbid")
    popsize: Annotated[int | None, Strict(), Field(ge=2)] = None
    sigma0: Annotated[float, Field(gt=0.0)] = 0.3


def _prompted(name: str, title: str, preset: str) -> Method:
    return Method(name, MethodKind.PROMPTED, title, PRESETS[preset], phase="props_phase", top_k_prompt=True)


def _rl(algo: str) -> Method:
    from .baselines.algorithms import ALGORITHMS  # plain data: no torch

    title = f"{ALGORITHMS[algo].title} (Stable-Baselines3, default hyperparameters)"
    return Method(f"rl-{algo}", MethodKind.RL, title, algo=algo, iteration_unit="timesteps")


# In the order of the paper's tables (and of the report's columns).
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        _prompted("vanilla", "Vanilla ProPS: raw parameters and rewards, optimum disclosed", "vanilla"),
        Method("r2po", MethodKind.PROMPTED, "R2PO: Search-LLM proposal, Critic-LLM revision from rollouts", PRESETS["vanilla"],
               default_episodes=20, iteration_unit="LLM calls (two per two-stage iteration)", phase="r2po_phase",
               raw_evidence=True, forms=("auto", CHAT_FORM), parallel=False),
        _prompted("pe", "PE-ProPS: encoded parameters", "pe"),
        _prompted("df", "DF-ProPS: detailed feedback (reward components, diagnostics)", "df"),
        _prompted("pp", "PP-ProPS: encoded parameters, scaled rewards, detailed feedback, no optimum", "pp"),
        _prompted("pp-hardened", "PP-ProPS with the side channels of docs/threat-model.md closed", "pp-hardened"),
        Method("random", MethodKind.BLACK_BOX, "random search: uniform samples in the box", iteration_unit="samples",
               phase="random_phase"),
        Method("cmaes", MethodKind.BLACK_BOX, "CMA-ES (pycma), raw or encoded space", iteration_unit="samples",
               phase="cmaes_phase", options=CMAESOptions),
        _rl("ppo"),
        _rl("a2c"),
        _rl("sac"),
        _rl("td3"),
        _rl("ddpg"),
        _rl("trpo"),
        _rl("dqn"),
    )
}  # fmt: skip


def register_method(method: Method) -> Method:
    """Add ``method`` to this process's registry (after the built-in ones) and return it.

    From then on ``--method`` (of ``ppprops.cli.main`` called in this process),
    ``ppprops.search(method=...)``, the experiment specs and the reports of this process know it.
    Another process (a shell's ``ppprops run``, ``ppprops show RUN``, the runs of a grid) knows it
    only if it registers it too: call this from a module named by a ``ppprops.plugins`` entry point
    of an installed package (``ppprops.plugins``; docs/architecture.md, "Recipe: add a method").
    A search method needs a ``phase``. Raises ConfigError if the name is taken or a search method
    has no phase builder.
    """
    if method.name in METHODS:
        raise ConfigError(f"a method named {method.name!r} is already registered")
    if method.is_search and method.phase is None:
        raise ConfigError(f"method {method.name!r} is a search and needs a phase builder")
    METHODS[method.name] = method
    return method


def methods(kind: MethodKind | None = None, *, search: bool | None = None) -> Iterator[Method]:
    """The methods registered so far, in table order, optionally of one kind, or only searches
    (``search=True``). Plugins not yet loaded are not listed (``search_method_names`` loads them)."""
    for m in METHODS.values():
        if (kind is None or m.kind is kind) and (search is None or m.is_search == search):
            yield m


class MethodChoices(Collection[str]):
    """The ``ppprops run --method`` choices: every search method, the plugins' included.

    A membership test of a registered name (``"pp" in choices``) loads no plugin; a name not yet
    registered, ``len`` and iteration load the plugins first (``ppprops.plugins.load_plugins``),
    so a command line naming a built-in method never scans the installed packages. Raises
    ConfigError, as ``load_plugins`` does, when a plugin fails to load.
    """

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        m = find_method(name)
        return m is not None and m.is_search

    def __iter__(self) -> Iterator[str]:
        load_plugins()
        return iter([m.name for m in methods(search=True)])

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def __bool__(self) -> bool:
        return True  # the built-in methods are always there; no plugin load to say so

    def __repr__(self) -> str:
        return f"MethodChoices({list(self)!r})"


def search_method_names() -> MethodChoices:
    """The ``ppprops run --method`` choices, the plugins' methods included (a lazy ``MethodChoices``)."""
    return MethodChoices()


def find_method(name: str) -> Method | None:
    """The method a run stores as ``name`` (``rl-<algo>`` for RL baselines), or None if unknown.

    A name not registered in this process loads the ``ppprops.plugins`` entry points once
    (``ppprops.plugins.load_plugins``) before it counts as unknown. Raises ConfigError when a
    plugin fails to load.
    """
    m = METHODS.get(name)
    if m is None:
        load_plugins()
        m = METHODS.get(name)
    return m


def get_method(name: str) -> Method:
    """Like ``find_method``; an unknown name is a ConfigError listing the choices."""
    m = find_method(name)
    if m is None:
        raise ConfigError(f"unknown method {name!r}; choose one of {', '.join(search_method_names())} "
                          f"(RL baselines: ppprops baseline rl --algo {'|'.join(rl_algos())})")  # fmt: skip
    return m


def rl_algos() -> list[str]:
    """The ``ppprops baseline rl --algo`` choices."""
    return [m.algo for m in methods(MethodKind.RL) if m.algo is not None]


def rl_method(algo: str) -> Method:
    """The RL baseline trained by ``--algo algo``; unknown algos are a ConfigError."""
    m = METHODS.get(f"rl-{algo}")
    if m is None or m.kind is not MethodKind.RL:
        raise ConfigError(f"--algo must be one of {', '.join(rl_algos())}, got {algo!r}")
    return m
