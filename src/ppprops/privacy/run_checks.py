"""The audit's run-level checks (``privacy.audit``): what the run as a whole tells the provider.

The request bodies are read one by one (``privacy.request_body``); these checks look at what the
requests showed, taken together: the known side channels of the shown history (``channels``,
``anchors``), the provider's clock (``timing``), where a target return ended the search (``stop``), the names of the user's own env (``identifiers``)
and every attack on the transcript (``exposure``). Each takes the auditor (``RunFacts``: what it
has read so far and where its findings go) and adds its findings to it in a fixed order.
"""
from __future__ import annotations

import itertools
import math
import re
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..client.secrets import Secrets
from ..config import RunConfig
from ..methods import Mechanisms
from ..store import Candidate
from ..tasks.base import Task
from .exposure import Assessment, assess
from .knowledge import facts_for
from .requests import Request
from .runseed import find_run_seed
from .simfit import SimLimits
from .simulator import env_is_public
from .tokens import token_value
from .view import Estimate, same_marker, view_of


class RunReport(Protocol):
    """The parts of the audit's report (``AuditReport``) the run-level checks fill in."""

    notes: list[str]
    not_run: list[tuple[str, str]]
    sim_bound: str
    public_dynamics: str
    estimates: list[Estimate]
    near_misses: list[str]


class RunFacts(Protocol):
    """What the run-level checks read of the auditor: the run, its requests, what they showed."""

    config: RunConfig
    mech: Mechanisms
    task: Task
    cands: list[Candidate]
    calls: list[dict[str, Any]]
    requests: list[Request]
    secrets: Secrets | None
    limits: SimLimits
    simulate: bool
    keyed_streams: bool
    told: list[tuple[float, Candidate]]
    shown: dict[int, Candidate]
    shown_diagnostics: dict[int, dict[str, str]]

    @property
    def report(self) -> RunReport:
        """The report being written."""

    def finding(self, severity: str, kind: str, detail: str, where: str, *, by_design: bool = False) -> None:
        """Count one occurrence of a finding at ``where``."""


# -- run-level channels -------------------------------------------------------------------
def channels(a: RunFacts) -> None:
    """The known side channels of the shown history: diagnostics that determine a raw value, the
    raw warm-up (its scale and its run seed), the lattice of integer returns, returns at a public cap."""
    mech, shown = a.mech, list(a.shown.values())
    if not shown:
        return
    if mech.scale_rewards and mech.detailed_feedback:
        _determined(a, shown)
    if mech.encode_params and not mech.encoded_warmup and any(c.source == "warmup" for c in shown):
        a.finding("channel", "warmup_scale", "warm-up drawn uniformly from the public box: max|theta~_j| over it estimates "
                  "a_j times the box bound", f"{sum(c.source == 'warmup' for c in shown)} warm-up entries shown")
    if mech.encode_params and not mech.encoded_warmup and not a.keyed_streams and any(c.source == "warmup" for c in shown):
        a.finding("channel", "run_seed", "the raw warm-up is drawn from the run seed: a provider that guesses a small "
                  "run seed replays it (runs made before streams were keyed by the secrets)",
                  f"run seed of {a.config.seed.bit_length()} bits")
    rets = [c.ret for c in shown]
    if mech.scale_rewards and not mech.warp_rewards and len(set(rets)) >= 3:
        if facts_for(a.task).integer_returns or all(float(r).is_integer() for r in rets):
            a.finding("channel", "reward_lattice", "integer returns scaled by c keep a lattice: the gcd of differences of "
                      "printed returns gives c", f"{len(set(rets))} distinct returns shown")
    if mech.scale_rewards and not mech.warp_rewards and not mech.secret_offsets:
        caps = {c.value for c in facts_for(a.task).caps or ()}
        if a.task.optimal_return is not None:
            caps.add(float(a.task.optimal_return))
        for c in shown:
            if c.ret in caps and c.ret != 0:
                a.finding("channel", "known_cap", f"a return at the public cap {c.ret:g} gives c = printed / {c.ret:g}",
                          f"candidate {c.index}")


def anchors(a: RunFacts) -> None:
    """Shown entries whose shown diagnostic marks an episode end at a public cap (the task's
    ``privacy.caps``) while their raw return is that cap: the diagnostic pins the raw return
    exactly (CartPole ``termination=time_limit``: 500; Acrobot ``success=0``: -500), whatever
    the reward map. Exposed (the best shown one is named), since a raw return is recovered
    exactly; ``hide_anchors`` withholds those diagnostics."""
    if not a.mech.scale_rewards or not a.shown:
        return
    best = max(a.shown.values(), key=lambda c: c.ret)
    for cap in facts_for(a.task).caps or ():
        pinned = [c for c in a.shown.values()
                  if same_marker(a.shown_diagnostics.get(c.index, {}).get(cap.diagnostic), cap.marker)
                  and math.isclose(c.ret, cap.value, rel_tol=1e-9, abs_tol=1e-9)]
        if not pinned:
            continue
        which = "the best shown policy's raw return" if best in pinned else "a shown raw return"
        a.finding("exposed", "anchored_return",
                  f"recovers {which} exactly: {cap.diagnostic}={cap.marker} marks an episode end at the public cap, "
                  f"raw return {cap.value:g} ({len(pinned)} of {len(a.shown)} shown entries; --hide-anchors on "
                  "withholds it)", ", ".join(f"candidate {c.index}" for c in sorted(pinned, key=lambda c: c.index)),
                  by_design=not a.mech.hardened)


def timing(a: RunFacts) -> None:
    """The provider's clock (``privacy.timing``): do the gaps between an answer and the next
    request follow the candidates' episodes? A channel when significantly so; exposed when the
    gap, calibrated on the run, gives the best shown raw return within 1%."""
    if not a.mech.scale_rewards or not a.shown:
        return
    from . import timing as clock

    pure = not a.mech.warp_rewards and not a.mech.secret_offsets
    got = clock.measure(a.calls, a.told, list(a.shown), c=a.secrets.c if a.secrets is not None else None,
                        pure_scale=pure, width=max(1, int(getattr(a.config, "parallel", 1))))
    paced = " (requests paced)" if a.mech.pace_requests else ""
    if isinstance(got, str):
        a.report.notes.append(f"request timing not measured: {got}")
        return
    a.report.notes.append(f"request timing{paced}: Spearman {got.rho_steps:+.2f} with the episode steps, {got.rho_return:+.2f} "
                          f"with the raw return over {len(got.gaps)} gaps (p = {got.p:.2g})")
    if got.best_error is not None and got.best_error <= 0.01 and got.significant:
        a.finding("exposed", "request-timing", f"recovers the best shown policy's raw return to {100 * got.best_error:.2g}%: "
                  f"{got.describe()}", "request times", by_design=not a.mech.hardened)
    elif got.significant:
        if got.best_error is not None and got.best_error <= 0.02:
            a.report.near_misses.append(f"request timing: the best shown raw return within {100 * got.best_error:.3g}%")
        a.finding("channel", "request_timing", got.describe() + (paced or "; --pace-requests on pads the gaps"),
                  "request times")


def stop(a: RunFacts) -> None:
    """A search that a target return ended (``ppprops.stopping``): its requests end right after the
    candidate that reached the target, so the provider may read that the last proposal's raw
    return is at least the target (the user's choice, often a public task's solved threshold). A
    channel unless a hardening delayed the stop by a keyed number of candidates."""
    target = a.config.stop.target_return
    search = [c for c in a.cands if c.reevaluates is None]
    hit = next((c for c in search if math.isfinite(c.ret) and c.ret >= target), None) if target is not None else None
    if hit is None or not a.calls or hit.source in ("warmup", "init") or len(search) >= a.config.warmup + a.config.iterations:
        return
    if a.mech.hardened:
        a.report.notes.append(f"stop: the target return ended the search {search[-1].index - hit.index} candidates after the one that "
                              "reached it (a keyed delay)")
        return
    a.finding("channel", "stop_at_target", f"the requests end right after candidate {hit.index}, the first whose raw return reached "
              f"the target return: the provider may read that its last proposal's raw return is at least the target "
              "(pp-hardened delays the stop by a keyed number of candidates)", f"candidate {hit.index}")


def _determined(a: RunFacts, shown: list[Candidate]) -> None:
    """Numeric diagnostics that, together, are an exact affine function of the raw return or a component."""
    names = sorted({k for r in a.requests for e in r.entries for k, t in e.diagnostics if token_value(t) is not None})
    targets: list[tuple[str, list[float]]] = [("the raw return", [c.ret for c in shown])]
    for k in sorted({k for c in shown for k in c.feedback.components}):
        targets.append((f"the raw component {k}", [c.feedback.components.get(k, 0.0) for c in shown]))
    for label, y in targets:
        yv = np.asarray(y, dtype=np.float64)
        if len(set(y)) < 3:
            continue
        for size in (1, 2):
            hits = []
            for subset in itertools.combinations(names, size):
                cols = [[_num(c.feedback.diagnostics.get(n)) for n in subset] for c in shown]
                X = np.asarray(cols, dtype=np.float64)
                if not np.all(np.isfinite(X)):
                    continue
                A = np.column_stack([X, np.ones(len(shown))])
                if np.linalg.matrix_rank(A) < A.shape[1] or len({tuple(r) for r in X}) < size + 2:
                    continue
                coef, *_ = np.linalg.lstsq(A, yv, rcond=None)
                if np.max(np.abs(A @ coef - yv)) <= 1e-6 * max(1.0, float(np.max(np.abs(yv)))):
                    coef = np.round(coef, 6) + 0.0
                    formula = " + ".join(f"{b:g}*{n}" for b, n in zip(coef[:-1], subset, strict=True)) + f" + {coef[-1]:g}"
                    hits.append(f"diagnostic{'s' if size > 1 else ''} {', '.join(subset)} determine{'' if size > 1 else 's'} "
                                f"{label}: {label.split()[-1]} = {formula}")
            for h in hits:
                a.finding("channel", "diagnostic_determines", h, f"{len(shown)} shown candidates")
            if hits:
                break


def _num(v: object) -> float:
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


# -- the attacks on the transcript ----------------------------------------------------------
def exposure(a: RunFacts) -> None:
    """Run and score every attack (``exposure.assess``): exposures, attacks not run, the
    public-dynamics line and the run seed read off the transcript."""
    if not a.requests or not (a.mech.encode_params or a.mech.scale_rewards):
        return
    if a.simulate:
        a.report.sim_bound = a.limits.describe()
    found = assess(a.requests, a.task, a.config.box, a.mech, a.cands, a.secrets, limits=a.limits,
                   simulate=a.simulate, grid=run_grid_factor(a.config, a.secrets))
    for x in found.exposures:
        if x.target == "c":
            secret = "c"
        elif x.target == "a":
            secret = f"a_j on {x.coords} of {a.task.D} coordinates"
        elif x.target == "raw params":
            secret = "the best shown policy's raw parameters (largest error as a share of the box width)"
        else:
            secret = f"the best shown policy's {x.target}"
        a.finding("exposed", x.attack, f"recovers {secret} to {100 * x.error:.2g}%: {x.detail}", "transcript",
                  by_design=x.paper)
    a.report.not_run = found.not_run
    a.report.near_misses += found.near_misses
    a.report.estimates = found.estimates
    if found.note:
        a.report.notes.append(found.note)
    a.report.public_dynamics = _public_dynamics(a, found)
    _seed_channel(a, found)


def _public_dynamics(a: RunFacts, found: Assessment) -> str:
    """The line for a task whose env the provider can build: what the simulator fits got here."""
    if not a.mech.encode_params or not env_is_public(a.task):
        return ""
    got = []
    for x in found.exposures:
        if x.attack.startswith("sim-"):
            got.append(f"{x.attack}: {x.target} within {100 * x.error:.2g}%")
    for o in found.simulated:
        if o.error is not None and not any(g.startswith(f"{o.attack}: {o.target} ") for g in got):
            got.append(f"{o.attack}: {o.target} within {100 * o.error:.3g}% (prior {100 * (o.prior_error or 0):.3g}%)")
    ran = "; here " + ", ".join(got) if got else ""
    return (f"task {a.task.name} runs the public env {a.task.env_id}, so the provider can simulate it: the encodings "
            f"protect the secrets only as far as the shown history leaves them undetermined, whatever the preset "
            f"(docs/threat-model.md, 'What the encoding cannot hide'){ran}")


def _seed_channel(a: RunFacts, found: Assessment) -> None:
    """The run seed read off the transcript (any preset that encodes parameters): it replays the warm-up
    draws and gives every episode's initial state."""
    if not a.mech.encode_params or not a.requests:
        return
    v = view_of(a.requests, a.task, a.config.box)
    seed, how = find_run_seed(v)
    if seed is not None:
        a.finding("channel", "run_seed", f"the run seed is read off the transcript ({how}): it gives every episode's "
                  "initial state (seeding.episode_seeds) and the warm-up draws", "transcript")


def run_grid_factor(config: RunConfig, secrets: Secrets | None) -> float:
    """The secret grid factor g of a run on the grid (``client.codec.grid_factor``), 1 off the grid or
    without its key file: attacks on a are scored against the effective scale g a_j."""
    if secrets is None or config.numbers != "grid":
        return 1.0
    from ..client.codec import grid_factor

    return grid_factor(secrets, config.box, config.mechanisms.warp_params)


# -- the user's own names --------------------------------------------------------------------
def identifiers(a: RunFacts) -> None:
    """Names of the task's own env (its module, class, file and folder names, from the stored
    declaration) must not reach a prompt under a preset that encodes parameters."""
    if not a.mech.encode_params or env_is_public(a.task):
        return
    names = env_identifiers(a.task)
    if not names:
        return
    for req in a.requests:
        text = req.body or req.text
        for name in names:
            if re.search(rf"(?<![A-Za-z0-9_]){re.escape(name)}(?![A-Za-z0-9_])", text):
                a.finding("identifier", "identifier", f"the name '{name}' of the task's own env ({names[name]})",
                          req.where)


IGNORED_NAMES = frozenset({"env", "envs", "environment", "environments", "gym", "gymnasium", "src", "lib", "main",
                           "__main__", "site-packages", "python", "test", "tests", "make", "ppprops", "home", "user",
                           "users", "tmp", "robot", "policy", "task"})


def env_identifiers(task: Any) -> dict[str, str]:
    """name -> what it is: the module path and each of its parts, the class or factory name, the
    imported modules, the folders (and their last two path components) of the task's env, from its
    stored declaration (``EnvRecipe``: id, entry_point, imports, paths). Names shorter than three
    characters and generic words (``IGNORED_NAMES``) are left out."""
    spec = getattr(task, "spec", None)
    env = getattr(spec, "env", None)
    found: dict[str, str] = {}

    def add(name: str, what: str) -> None:
        name = name.strip()
        if len(name) >= 3 and name.lower() not in IGNORED_NAMES and name not in found:
            found[name] = what

    def module(ref: str, what: str) -> None:
        mod, sep, attr = ref.partition(":")
        if sep:
            add(mod, f"{what} module")
            for part in mod.split("."):
                add(part, f"{what} module")
            for part in attr.split("."):
                add(part, f"{what} name")
        else:
            add(ref, f"{what} module")
            for part in ref.split("."):
                add(part, f"{what} module")

    ids = [getattr(env, "id", None) or task.env_id]
    for ref in ids:
        if ref and ":" in ref:
            module(ref, "env id")
    if env is not None:
        if env.entry_point:
            module(str(env.entry_point), "entry point")
        for m in env.imports:
            module(str(m), "imported")
        for path in env.paths:
            parts = Path(str(path)).parts
            for part in parts[-2:]:
                add(part, "folder")
    return found

