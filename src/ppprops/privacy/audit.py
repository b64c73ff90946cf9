"""``ppprops audit DIR``: does any recorded request hold a raw value the preset promises to hide?

How it decides (docs/privacy.md, "The audit"). Every byte of every recorded request body is
accounted for:

- every top-level field must be what the client sets at that call (model, sampling settings, the
  token budget, the structured output, the key-derived seed), as its own ``RequestShape``
  replayed on the recorded exchanges says: a parameter the endpoint refused is gone or renamed
  from then on, the budget grows once the endpoint is seen to reason, each session (a resume)
  starts afresh; any other field or value is **unverified**, and every number in it, at any
  precision, integers included, is compared with every raw value (a match: **leak**);
- every message of any role, as ``wire.turns`` builds them: [prompt], or after an unusable
  answer [prompt, that answer's final text, correction] or [prompt + correction], the fault
  re-derived from the recorded answer (and the history shown, for a repeated policy). The echoed
  final text is the provider's own and must equal it exactly; whatever differs from the rebuilt
  text, and any message in another arrangement, is read the same way;
- the prompt is rebuilt from the public context and the stored encoded values of the candidates
  it shows (``privacy.reconstruct``), so every stretch the templates do not produce is read;
- each history entry is matched to the candidate it shows and each printed field compared with
  the raw and the encoded value of the same quantity at its printed precision: raw but not
  encoded is a leak, both a counted coincidence, neither unverified. Fields a preset sends raw
  by design (vanilla, df, R2PO's critic evidence) are leaks marked "by design".

Then every attack of ``privacy.attacks`` runs on the requests (the simulator attacks, which also
build the task's env when it is public, within ``simfit.SimLimits``, stated in the report): one
that recovers a hidden secret within 1% (scored against the key file, or the store for pure
scales), or the best shown policy's raw return or parameters within 1%, makes the run
**exposed**, marked when the channel is one the paper's scheme keeps. Known side channels without
such a recovery are reported as **channels** (warnings); attacks that could not run are listed
with why. Under a preset that encodes parameters, a name of the user's own env (module, class,
file, folder) in any request is an **identifier** finding.

Exit code: 0 when nothing leaked, no identifier was sent, everything was accounted for and nothing
is exposed; 1 with the locations otherwise; ``--strict`` also fails on channels. Request timing is
measured on the recorded request times (``privacy.timing``: a channel when the gaps between an
answer and the next request follow the episodes, exposed when the calibrated clock gives the best
shown raw return within 1%); request sizes are not checked (named in every report).

``audit_run(..., attacks=False)`` is the quick audit a finished run prints about itself: every
check above but the attacks (no exposure, no public-dynamics line, no run seed read off the
transcript); its report says so and its verdict is never CLEAN.
"""
from __future__ import annotations

import bisect
import itertools
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import seeding
from ..client.secrets import Secrets
from ..config import RunConfig
from ..errors import StoreError
from ..methods import Mechanisms
from ..proposers.llm import StallCounter
from ..rundir import open_run
from ..store import Candidate
from ..wire.encoded import EncodedEntry
from ..wire.forms import CHAT, CRITIC, ENDPOINT_COMPLETIONS, FORMS, FormRequest, PromptForm
from ..wire.transcript import ShownEntry, number_tokens, outside_entries
from ..wire.turns import REPEATS_HISTORY
from . import reconstruct as rc
from . import simfit
from .exposure import Assessment, assess
from .knowledge import facts_for
from .requests import Request, message_text, parse_request
from .runseed import find_run_seed
from .simfit import SimLimits
from .simulator import env_is_public
from .tokens import renders, token_value
from .view import Estimate, same_marker, view_of

MAX_LOCATIONS = 5  # locations listed per finding; the count covers all
TIMING_KINDS = ("request-timing", "request_timing")  # the clock exposed (its calibration gives the best raw return), and as a channel
# Every top-level field the client may send in some state of its request shape (``RequestShape``),
# besides the sampling fields the forms choose; and the fields the shape alone decides.
SENT_FIELDS = frozenset({"model", "messages", "prompt", "temperature", "max_tokens", "max_completion_tokens", "seed", "reasoning_effort",
                         "response_format", "grammar", "stop", "top_p", "min_p", "top_k"})
_SHAPE_FIELDS = frozenset({"model", "max_tokens", "max_completion_tokens", "seed", "reasoning_effort"})
NOT_CHECKED = "request sizes, token counts, and the provider's own answers"


@dataclass
class Finding:
    """One kind of problem in one field, with where it was seen (first few places) and how often."""

    severity: str  # leak | identifier | unverified | exposed | channel
    kind: str
    detail: str
    by_design: bool = False
    locations: list[str] = field(default_factory=list)
    count: int = 0

    def add(self, where: str) -> None:
        """Count one more occurrence at ``where``; the first MAX_LOCATIONS places are kept."""
        self.count += 1
        if len(self.locations) < MAX_LOCATIONS:
            self.locations.append(where)

    def to_json(self) -> dict[str, Any]:
        """The finding as a JSON object (severity, kind, detail, by_design, count, locations)."""
        return {"severity": self.severity, "kind": self.kind, "detail": self.detail, "by_design": self.by_design,
                "count": self.count, "locations": self.locations}


@dataclass
class AuditReport:
    """The outcome of ``audit_run``: what was read, and every finding, worst severity first.

    ``requests`` and ``entries`` count the requests and the history entries read; ``unanswered``
    lists the call ids of those recorded before they were sent and never answered (read like the
    others); ``checked`` counts the printed values compared, by kind (params, return, components,
    diagnostics); ``coincidences`` counts printed values equal to both the raw and the encoded
    value. The paper's promise it checks: only theta~ = A theta and r~ = c r (Sec. II-B, II-C,
    Eq. 5, 7, 8) reach the LLM.
    """

    run_dir: str
    method: str
    mechanisms: dict[str, bool]
    requests: int = 0
    unanswered: list[int] = field(default_factory=list)
    entries: int = 0
    checked: dict[str, int] = field(default_factory=lambda: {"params": 0, "return": 0, "components": 0, "diagnostics": 0})
    coincidences: int = 0
    findings: list[Finding] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    not_run: list[tuple[str, str]] = field(default_factory=list)  # (attack, why it could not run)
    sim_bound: str = ""  # the budget of the simulator attacks, in words
    public_dynamics: str = ""  # the line naming a task whose env the provider can simulate
    estimates: list[Estimate] = field(default_factory=list, repr=False)  # every attack's estimate (not in the JSON)
    attacked: bool = True  # the attacks ran (``audit_run(attacks=False)``: the transcript checks only)
    near_misses: list[str] = field(default_factory=list)  # attacks within 2% but not 1%: named in the verdict

    def _of(self, severity: str) -> list[Finding]:
        return [f for f in self.findings if f.severity == severity]

    @property
    def leaks(self) -> list[Finding]:
        """Findings where a raw value was sent (by design for the presets that send raw values)."""
        return self._of("leak")

    @property
    def unverified(self) -> list[Finding]:
        """Findings of request content the client's code would not produce from encoded values."""
        return self._of("unverified")

    @property
    def channels(self) -> list[Finding]:
        """Known side channels with no secret recovered (warnings; failures only under ``strict``)."""
        return self._of("channel")

    @property
    def identifiers(self) -> list[Finding]:
        """Findings where a name of the user's own env (module, class, file, folder) was sent."""
        return self._of("identifier")

    @property
    def exposed(self) -> list[Finding]:
        """Transcript-only attacks that recovered a secret (``c`` or some ``a_j``) within 1%."""
        return self._of("exposed")

    @property
    def clean(self) -> bool:
        """True with no leak, no identifier, nothing unverified and nothing exposed (channels allowed).

        Without the attacks (``attacked`` false) nothing can be exposed: then it speaks for the
        transcript checks only, and ``verdict`` says so."""
        return not self.leaks and not self.identifiers and not self.unverified and not self.exposed

    def exit_code(self, strict: bool = False) -> int:
        """``ppprops audit``'s exit code: 0 when clean (and, with ``strict``, no channel), else 1."""
        return 0 if self.clean and not (strict and self.channels) else 1

    def verdict(self, strict: bool = False) -> str:
        """One line naming the worst outcome: LEAK, IDENTIFIERS, UNVERIFIED, EXPOSED, CHANNELS (``strict`` only) or
        CLEAN; without the attacks NOTHING RAW SENT where it would say CLEAN (or CHANNELS)."""
        if self.leaks:
            design = all(f.by_design for f in self.leaks)
            kinds = ", ".join(sorted({f.kind for f in self.leaks}))
            why = f" (by design of preset {self.method})" if design else ""
            return f"LEAK: raw values were sent{why}: {kinds}"
        if self.identifiers:
            names = ", ".join(sorted({f.detail.split("'")[1] for f in self.identifiers if "'" in f.detail}))
            return f"IDENTIFIERS: names of the task's own env (module, class, file or folder) reached the provider: {names}"
        if self.unverified:
            return (f"UNVERIFIED: {sum(f.count for f in self.unverified)} place(s) in the requests hold something the client's "
                    "code does not produce from encoded values")
        if self.exposed:
            what = ", ".join(dict.fromkeys(f"{f.kind} ({f.detail.split(':')[0]})" for f in self.exposed))
            paper = all(f.by_design for f in self.exposed)
            clock = ", with --pace-requests on for the request timing" if any(f.kind in TIMING_KINDS for f in self.exposed) else ""
            why = (f" These are channels PP-ProPS keeps as the paper defines it (pp-hardened closes them{clock})."
                   if paper and self.method == "pp" else "")
            return f"EXPOSED: no raw value was sent, but attacks on the transcript recover secrets or raw values within 1%: {what}.{why}"
        n = len(self.channels)
        tail = f"; {n} known channel(s) remain (warnings)" if n else ""
        if not self.attacked:
            return (f"NOTHING RAW SENT: no raw parameter, return, reward component or optimal return was sent{tail}; the attacks "
                    "on the transcript did not run")
        near = f"; near miss (within 2%, not 1%): {', '.join(self.near_misses)}" if self.near_misses else ""
        if strict and n:
            return f"CHANNELS (strict): no raw value was sent, but {n} known channel(s) remain{near}"
        return f"CLEAN: no raw parameter, return, reward component or optimal return was sent{tail}{near}"

    def to_json(self, strict: bool = False) -> dict[str, Any]:
        """The ``ppprops audit --json`` object: the counts, the verdict, the exit code and every finding."""
        return {"run_dir": self.run_dir, "method": self.method, "mechanisms": self.mechanisms, "requests": self.requests,
                "unanswered": self.unanswered, "entries": self.entries, "checked": self.checked, "coincidences": self.coincidences,
                "verdict": self.verdict(strict), "exit_code": self.exit_code(strict),
                "findings": [f.to_json() for f in self.findings], "notes": self.notes,
                "not_run": [{"attack": a, "why": w} for a, w in self.not_run], "simulator_bound": self.sim_bound,
                "public_dynamics": self.public_dynamics, "attacked": self.attacked, "near_misses": self.near_misses}

    def format(self, strict: bool = False) -> str:
        """The text ``ppprops audit`` prints: counts, verdict, what is not checked, one line per finding."""
        c = self.checked
        ids = ", ".join(map(str, self.unanswered))
        never = f" ({len(self.unanswered)} never answered: call{'s' if len(self.unanswered) > 1 else ''} {ids})" if self.unanswered else ""
        lines = [
            f"audit of {self.run_dir} (method {self.method}): {self.requests} requests{never}, {self.entries} history entries; "
            f"checked {c['params']} parameters, {c['return']} returns, {c['components']} components, {c['diagnostics']} diagnostics "
            f"({self.coincidences} coincidental equalities of raw and encoded values)",
            f"verdict: {self.verdict(strict)}",
            f"not checked: {NOT_CHECKED}",
        ]
        if not self.attacked:
            lines.append(f"attacks: not run (the transcript checks only; ppprops audit {self.run_dir} runs them)")
        if self.public_dynamics:
            lines.append(f"public dynamics: {self.public_dynamics}")
        if self.sim_bound:
            lines.append(f"simulator attacks: bounded by {self.sim_bound}")
        if self.not_run:
            lines.append("attacks not run: " + "; ".join(f"{a} ({w})" for a, w in self.not_run))
        lines += [f"note: {n}" for n in self.notes]
        for f in self.findings:
            design = " (paper's scheme)" if f.severity == "exposed" else " (by design)"
            tag = f"{f.severity}{design if f.by_design else ''}"
            where = "; ".join(f.locations) + (" ..." if f.count > len(f.locations) else "")
            lines.append(f"  {tag:<18} {f.kind:<22} {f.detail} [{f.count}x: {where}]")
        return "\n".join(lines)


class _Auditor:
    def __init__(self, run_dir: Path, config: RunConfig, candidates: Sequence[Candidate], calls: Sequence[dict[str, Any]],
                 secrets: Secrets | None = None, *, sessions: Sequence[int] | None = None,
                 endpoint_changes: Sequence[dict[str, Any]] = (), adaptations: Sequence[dict[str, Any]] = (),
                 limits: SimLimits | None = None, simulate: bool = True, keyed_streams: bool = False,
                 attacks: bool = True, told: Sequence[tuple[float, Candidate]] = ()) -> None:
        self.told = list(told)  # (when recorded, candidate): the request timing check
        self.limits = limits or simfit.DEFAULT_LIMITS
        self.attacks = attacks
        self.keyed_streams = keyed_streams  # the run's draws are keyed by its secrets (seeding.Streams): no seed replay
        self.simulate = simulate
        self.config = config
        self.mech: Mechanisms = config.mechanisms
        self.task = config.make_task()
        self.cands = list(candidates)
        self.calls = list(calls)
        self.requests = [parse_request(int(c["id"]), int(c["iteration"]), int(c["attempt"]), str(c["request"]), c.get("content"),
                                       c.get("form")) for c in self.calls]
        self.secrets = secrets
        self.codec = rc.client_codec(self.task, config, secrets)
        self._rebuilt: dict[str, rc.Rebuilt] = {}  # per prompt form: its context, and each candidate's entry built once
        self.rebuilt = self._rebuilt_for(FORMS[config.form])  # that of the call being read (``body``)
        self.ctx = self.rebuilt.ctx
        self.replay = rc.ClientReplay(config.llm, self.task.D, sessions, endpoint_changes)
        self.answered: dict[tuple[int, int], dict[str, Any]] = {}  # (iteration, attempt) -> its latest usable answer
        self.adaptations = [str(a.get("change")) for a in adaptations]
        self.report = AuditReport(str(run_dir), config.method, self.mech.to_json(), attacked=attacks)
        self._findings: dict[tuple[str, str, str], Finding] = {}
        D = self.task.D  # (N, D) even when nothing was evaluated yet (N = 0: a new study, a run stopped at its first reset)
        self.enc = np.array([c.params_enc for c in self.cands], dtype=np.float64).reshape(len(self.cands), D)
        self.raw = np.array([c.params for c in self.cands], dtype=np.float64).reshape(len(self.cands), D)
        self.shown: dict[int, Candidate] = {}  # candidates that appeared in some request
        self.shown_diagnostics: dict[int, dict[str, str]] = {}  # candidate -> each diagnostic as some request printed it
        self._problems = 0  # occurrences of findings other than channels so far (``prompt`` flags the entries that add some)
        counter = StallCounter()  # stall_count of every prefix of the candidates, counted once
        self._stalls = [0]
        for c in self.cands:
            counter.tell(c)
            self._stalls.append(counter.count)

    def _rebuilt_for(self, form: PromptForm) -> rc.Rebuilt:
        """The public prompt context of ``form`` (``reconstruct.context``) and its entries, built once per run."""
        if form.name not in self._rebuilt:
            self._rebuilt[form.name] = rc.Rebuilt(self.codec, rc.context(self.task, self.config, self.codec, form), form)
        return self._rebuilt[form.name]

    def _stall_count(self, n: int) -> int:
        """``stall_count`` of the candidates numbered below ``n`` (the trials settled when a request
        at trial ``n`` was built: failed trials are no candidates and never counted)."""
        return self._stalls[bisect.bisect_left([c.index for c in self.cands], n)]

    def _round_start(self, iteration: int) -> int:
        """The trial number at which the round of LLM iteration ``iteration`` began: with
        ``--parallel`` P its P requests share the history told before the round."""
        parallel = max(1, int(getattr(self.config, "parallel", 1)))
        return self.config.warmup + (iteration // parallel) * parallel

    def finding(self, severity: str, kind: str, detail: str, where: str, *, by_design: bool = False) -> None:
        key = (severity, kind, detail)
        if key not in self._findings:
            self._findings[key] = Finding(severity, kind, detail, by_design)
            self.report.findings.append(self._findings[key])
        self._findings[key].add(where)
        if severity != "channel":
            self._problems += 1

    # -- one printed scalar against its raw and encoded value ------------------------------------
    def scalar(self, tok: str, raw: float | None, enc: float | None, protected: bool, kind: str, label: str, where: str) -> None:
        parsed = token_value(tok)
        if parsed is None or raw is None or enc is None:
            self.finding("unverified", kind, f"{label} could not be compared ({tok!r})", where)
            return
        v, tol = parsed
        r, e = renders(raw, v, tol), renders(enc, v, tol)
        if r and (not protected or not e):
            self.finding("leak", kind, f"raw {label}", where, by_design=not protected)
        elif r and e:
            self.report.coincidences += 1
        elif not e:
            self.finding("unverified", kind, f"{label} is neither its raw nor its encoded value", where)

    # -- one history entry --------------------------------------------------------------------
    def match(self, vals: np.ndarray, tols: np.ndarray, shown: ShownEntry | None = None) -> tuple[int | None, str]:
        """The candidate whose parameters (encoded, else raw) the printed ``vals`` show, and which.

        A policy evaluated more than once (the LLM proposed it again) matches several candidates
        whose returns and diagnostics differ with the episode: among them, the one whose return,
        components and diagnostics, as printed in ``shown``, are its own (raw or encoded), else the
        one whose return is, else the first.
        """
        if not self.cands or vals.shape[0] != self.enc.shape[1]:
            return None, ""
        need = math.ceil(vals.shape[0] / 2)
        for name, matrix in (("encoded", self.enc), ("raw", self.raw)):
            score = np.sum(np.abs(matrix - vals) <= tols * (1 + 1e-9) + 1e-12, axis=1)
            best = int(score.max())
            if best < need:
                continue
            tied = [int(i) for i in np.flatnonzero(score == best)]
            if shown is not None and len(tied) > 1:  # max keeps the first of equal ranks
                return max(tied, key=lambda i: self._rank(self.cands[i], shown)), name
            return tied[0], name
        return None, ""

    @staticmethod
    def _fits(tok: str, raw: object, enc: object) -> bool:
        """The printed ``tok`` renders the raw or the encoded value (a word: is it, as printed)."""
        parsed = token_value(tok)
        if parsed is None:
            return any(x is not None and tok == str(x) for x in (raw, enc))
        return any(isinstance(x, (int, float)) and renders(float(x), *parsed) for x in (raw, enc))

    def _rank(self, c: Candidate, shown: ShownEntry) -> tuple[bool, bool]:
        """(every printed scalar of ``shown`` is ``c``'s own, its printed return is): the higher, the likelier ``c``."""
        ret = self._fits(shown.ret, c.ret, c.feedback_enc.ret)
        rest = all(self._fits(tok, c.feedback.components.get(key), c.feedback_enc.components.get(key))
                   for key, tok in shown.components) and all(
                   self._fits(tok, c.feedback.diagnostics.get(key), c.feedback_enc.diagnostics.get(key))
                   for key, tok in shown.diagnostics)  # fmt: skip
        return ret and rest, ret

    def entry(self, req: Request, k: int, e: ShownEntry) -> Candidate | None:
        """Check one shown entry; returns the candidate it shows, or None if it matches none."""
        where = f"{req.where}, entry {k + 1}"
        parsed = [token_value(t) for t in e.params]
        if any(p is None for p in parsed):
            self.finding("unverified", "entry", "history entry with unreadable parameters", where)
            return None
        vals = np.array([p[0] for p in parsed if p is not None])
        tols = np.array([p[1] for p in parsed if p is not None])
        idx, how = self.match(vals, tols, e)
        if idx is None:
            self.finding("unverified", "entry", "history entry that matches no evaluated candidate", where)
            return None
        c = self.cands[idx]
        self.shown[c.index] = c
        self.shown_diagnostics.setdefault(c.index, {}).update(dict(e.diagnostics))
        where = f"{where} = candidate {c.index}"
        self.report.entries += 1
        # parameters, position by position
        em = np.abs(c.params_enc - vals) <= tols * (1 + 1e-9) + 1e-12
        rm = np.abs(c.params - vals) <= tols * (1 + 1e-9) + 1e-12
        self.report.checked["params"] += len(vals)
        protected = self.mech.encode_params
        leak = rm if not protected else (rm & ~em)
        if leak.any():
            coords = ", ".join(str(j) for j in np.flatnonzero(leak)[:8]) + (" ..." if leak.sum() > 8 else "")
            self.finding("leak", "raw_param", f"raw parameter value(s) (params[{coords}])" if protected else "raw parameters",
                         where, by_design=not protected)
        if protected:
            self.report.coincidences += int((rm & em).sum())
        odd = ~rm & ~em
        if odd.any():
            self.finding("unverified", "raw_param", "parameters that are neither raw nor encoded", where)
        # return and components
        rewards = self.mech.scale_rewards
        self.report.checked["return"] += 1
        self.scalar(e.ret, c.ret, c.feedback_enc.ret, rewards, "raw_return", "return", where)
        for key, tok in e.components:
            self.report.checked["components"] += 1
            self.scalar(tok, c.feedback.components.get(key), c.feedback_enc.components.get(key), rewards, "raw_component",
                        f"reward component {key}", where)
        # diagnostics are not rewards; one that prints a raw reward-valued number is a known channel
        for key, tok in e.diagnostics:
            self.report.checked["diagnostics"] += 1  # a word too: the anchor check reads those
            parsed_d = token_value(tok)
            if parsed_d is None:
                continue
            if not rewards:
                continue
            v, tol = parsed_d
            if c.ret != 0 and renders(c.ret, v, tol) and not renders(c.feedback_enc.ret, v, tol):
                self.finding("channel", "diagnostic_return", f"diagnostic {key} equals the raw return", where)
            for ck, cv in c.feedback.components.items():
                if cv != 0 and renders(cv, v, tol) and not renders(c.feedback_enc.components.get(ck, math.nan), v, tol):
                    self.finding("channel", "diagnostic_return", f"diagnostic {key} equals the raw component {ck}", where)
        if c.clipped and protected and not self.mech.warp_params:
            self.finding("channel", "clip_edge", "a clipped candidate shows the encoded box edge (a_j times the public bound)", where)
        return c

    # -- prose: everything outside the history entries --------------------------------------------
    def prose(self, req: Request, text: str, entries: list[ShownEntry], skips: Sequence[int] = ()) -> None:
        optimum = self.task.optimal_return
        by_design = self.mech.disclose_optimum or self.mech.disclose_reward_structure
        # raw returns and components outside the entries are found by the rebuild (``spans``): text the
        # templates produce is public, and comparing it with raw values would only find coincidences
        for offset, part in outside_entries(text, entries):
            for pos, tok in number_tokens(part):
                if offset + pos in skips:
                    continue  # a number the form derives from the shown entries, checked by ``prompt``
                parsed = token_value(tok)
                if parsed is None:
                    continue
                v, tol = parsed
                where = f"{req.where}, prose at character {offset + pos}"
                if optimum is not None and renders(optimum, v, tol) and abs(optimum) >= 1:
                    self.finding("leak", "optimum", f"the optimal return {optimum:g} (printed {tok})", where, by_design=by_design)

    # -- run-level channels -------------------------------------------------------------------
    def channels(self) -> None:
        mech, shown = self.mech, list(self.shown.values())
        if not shown:
            return
        if mech.scale_rewards and mech.detailed_feedback:
            self._determined(shown)
        if mech.encode_params and not mech.encoded_warmup and any(c.source == "warmup" for c in shown):
            self.finding("channel", "warmup_scale", "warm-up drawn uniformly from the public box: max|theta~_j| over it estimates "
                         "a_j times the box bound", f"{sum(c.source == 'warmup' for c in shown)} warm-up entries shown")
        if mech.encode_params and not mech.encoded_warmup and not self.keyed_streams and any(c.source == "warmup" for c in shown):
            self.finding("channel", "run_seed", "the raw warm-up is drawn from the run seed: a provider that guesses a small "
                         "run seed replays it (runs made before streams were keyed by the secrets)",
                         f"run seed of {self.config.seed.bit_length()} bits")
        rets = [c.ret for c in shown]
        if mech.scale_rewards and not mech.warp_rewards and len(set(rets)) >= 3:
            if facts_for(self.task).integer_returns or all(float(r).is_integer() for r in rets):
                self.finding("channel", "reward_lattice", "integer returns scaled by c keep a lattice: the gcd of differences of "
                             "printed returns gives c", f"{len(set(rets))} distinct returns shown")
        if mech.scale_rewards and not mech.warp_rewards and not mech.secret_offsets:
            caps = {c.value for c in facts_for(self.task).caps or ()}
            if self.task.optimal_return is not None:
                caps.add(float(self.task.optimal_return))
            for c in shown:
                if c.ret in caps and c.ret != 0:
                    self.finding("channel", "known_cap", f"a return at the public cap {c.ret:g} gives c = printed / {c.ret:g}",
                                 f"candidate {c.index}")

    def anchors(self) -> None:
        """Shown entries whose shown diagnostic marks an episode end at a public cap (the task's
        ``privacy.caps``) while their raw return is that cap: the diagnostic pins the raw return
        exactly (CartPole ``termination=time_limit``: 500; Acrobot ``success=0``: -500), whatever
        the reward map. Exposed (the best shown one is named), since a raw return is recovered
        exactly; ``hide_anchors`` withholds those diagnostics."""
        if not self.mech.scale_rewards or not self.shown:
            return
        best = max(self.shown.values(), key=lambda c: c.ret)
        for cap in facts_for(self.task).caps or ():
            pinned = [c for c in self.shown.values()
                      if same_marker(self.shown_diagnostics.get(c.index, {}).get(cap.diagnostic), cap.marker)
                      and math.isclose(c.ret, cap.value, rel_tol=1e-9, abs_tol=1e-9)]
            if not pinned:
                continue
            which = "the best shown policy's raw return" if best in pinned else "a shown raw return"
            self.finding("exposed", "anchored_return",
                         f"recovers {which} exactly: {cap.diagnostic}={cap.marker} marks an episode end at the public cap, "
                         f"raw return {cap.value:g} ({len(pinned)} of {len(self.shown)} shown entries; --hide-anchors on "
                         "withholds it)", ", ".join(f"candidate {c.index}" for c in sorted(pinned, key=lambda c: c.index)),
                         by_design=not self.mech.hardened)

    def timing(self) -> None:
        """The provider's clock (``privacy.timing``): do the gaps between an answer and the next
        request follow the candidates' episodes? A channel when significantly so; exposed when the
        gap, calibrated on the run, gives the best shown raw return within 1%."""
        if not self.mech.scale_rewards or not self.shown:
            return
        from . import timing

        pure = not self.mech.warp_rewards and not self.mech.secret_offsets
        got = timing.measure(self.calls, self.told, list(self.shown), c=self.secrets.c if self.secrets is not None else None,
                             pure_scale=pure, width=max(1, int(getattr(self.config, "parallel", 1))))
        paced = " (requests paced)" if self.mech.pace_requests else ""
        if isinstance(got, str):
            self.report.notes.append(f"request timing not measured: {got}")
            return
        self.report.notes.append(f"request timing{paced}: Spearman {got.rho_steps:+.2f} with the episode steps, {got.rho_return:+.2f} "
                                 f"with the raw return over {len(got.gaps)} gaps (p = {got.p:.2g})")
        if got.best_error is not None and got.best_error <= 0.01 and got.significant:
            self.finding("exposed", "request-timing", f"recovers the best shown policy's raw return to {100 * got.best_error:.2g}%: "
                         f"{got.describe()}", "request times", by_design=not self.mech.hardened)
        elif got.significant:
            if got.best_error is not None and got.best_error <= 0.02:
                self.report.near_misses.append(f"request timing: the best shown raw return within {100 * got.best_error:.3g}%")
            self.finding("channel", "request_timing", got.describe() + (paced or "; --pace-requests on pads the gaps"),
                         "request times")

    def _determined(self, shown: list[Candidate]) -> None:
        """Numeric diagnostics that, together, are an exact affine function of the raw return or a component."""
        names = sorted({k for r in self.requests for e in r.entries for k, t in e.diagnostics if token_value(t) is not None})
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
                    self.finding("channel", "diagnostic_determines", h, f"{len(shown)} shown candidates")
                if hits:
                    break

    # -- every byte of a request body -----------------------------------------------------------
    def body(self, row: dict[str, Any], req: Request) -> None:
        """One recorded call, read as the prompt form it was recorded under (``wire.forms.FORMS``):
        its payload (the messages or the document) rebuilt and compared (``messages``, ``prompt``),
        every other field compared with the body the client builds for the request the form makes
        from public values (``FormRequest``, through the replayed ``RequestShape``), and the
        decisions recorded with the call checked by the form."""
        where = req.where
        form = FORMS.get(str(row.get("form")))
        self.rebuilt = self._rebuilt_for(form or CHAT)
        self.ctx = self.rebuilt.ctx
        try:
            doc = json.loads(str(row["request"]))
        except json.JSONDecodeError:
            doc = None
        if form is None:
            self.finding("unverified", "request", f"a call recorded under an unknown prompt form {row.get('form')!r}", where)
            self.free(doc if doc is not None else str(row["request"]), "", where)
            self.replay.observe(row, self._request(CHAT, req, []))
            return
        if not isinstance(doc, dict):
            self.free(str(row["request"]), "a request body that is not a JSON object", where)
            self.replay.observe(row, self._request(form, req, []))
            return
        key = "prompt" if form.endpoint == ENDPOINT_COMPLETIONS else "messages"
        shown: list[Candidate | None] = []
        if key not in doc:
            self.finding("unverified", "request", f"a request without {key}", where)
        elif key == "messages":
            shown = self.messages(doc[key], req, form)
        elif isinstance(doc[key], str):
            shown = self.prompt(doc[key], req, form)
        else:
            self.free(doc[key], f"a {form.name} prompt that is not a string", f"{where}, field {key}")
        verified = bool(shown) and all(c is not None for c in shown)
        entries = [self.rebuilt.entry(c) for c in shown if c is not None] if verified else []
        stalled = self._stall_count(self._round_start(req.iteration)) if self.config.explore is not False else 0
        want = self._request(form, req, entries, stalled)
        expected = self.replay.fields(want)  # what the client's request shape sends for it at this call
        decisions = row.get("decisions")
        if decisions is not None and verified:
            for problem in form.check_decisions(decisions, self.ctx, entries, iteration=req.iteration, attempt=req.attempt,
                                                temperature=self.config.llm.temperature, stalled=stalled):
                self.finding("unverified", "decisions", f"a recorded decision of the {form.name} form: {problem}", where)
        unrebuilt = "" if verified else " (the history it shows is not verified, so it cannot be rebuilt)"
        for name, value in doc.items():
            at = f"{where}, field {name}"
            if name == key:
                continue
            if name == "seed" and name in expected:
                self.seed(value, req)
            elif name in expected:
                if value != expected[name]:
                    self.free(value, f"field {name} differs from what the client sends{'' if name in _SHAPE_FIELDS else unrebuilt}", at)
            elif name in SENT_FIELDS:
                self.free(value, f"field {name}, which the client does not send at this point (its endpoint adaptations)", at)
            else:
                self.free(value, f"field {name}, which the client never sends", at)
        missing = [k for k in expected if k not in doc]
        if missing:
            self.finding("unverified", "request", f"a request without the field(s) {', '.join(missing)} the client sends", where)
        self.replay.observe(row, want)
        if row.get("ok"):
            self.answered[(req.iteration, req.attempt)] = row

    def _request(self, form: PromptForm, req: Request, entries: list[EncodedEntry], stalled: int = 0) -> FormRequest:
        """The request ``form`` makes at this call from what the proposer had: the public context,
        the entries shown, the settings, the stall count and, on a retry, the previous attempt's
        answer and the form's verdict on it (its payload is a placeholder: the payload is compared
        by ``messages`` / ``prompt``)."""
        previous = self.answered.get((req.iteration, req.attempt - 1)) if req.attempt > 0 else None
        content, detail = None, ""
        if previous is not None:
            finish, _ = rc.response_facts(previous.get("response"))
            content = previous.get("content")
            detail = form.judge(content, previous.get("reasoning"), self.ctx, entries, finish_reason=finish).detail
        return form.request(rc.PROMPT_MARK, ctx=self.ctx, shown=entries, iteration=req.iteration, attempt=req.attempt,
                            previous=content, detail=detail, temperature=self.config.llm.temperature, stalled=stalled)

    def seed(self, value: object, req: Request) -> None:
        at = f"{req.where}, field seed"
        if value is None:
            return
        if not isinstance(value, int) or isinstance(value, bool):
            self.free(value, "field seed that is not an integer", at)
            return
        if value == seeding.llm_seed(self.config.seed, req.iteration, req.attempt):
            self.finding("channel", "run_seed", "the request's sampling seed derives from the run seed (runs made before "
                         "sampling seeds were keyed by the secrets): trying run seeds finds it", at)
            return
        if self.secrets is not None and value != self.codec.sampling_seed(self.config.seed, req.iteration, req.attempt):
            self.free(value, "field seed that is not the key-derived sampling seed", at)
        elif self.secrets is None:
            self.free(value, "", at)  # not verifiable without the key file: still read for raw values

    def messages(self, value: object, req: Request, form: PromptForm) -> list[Candidate | None]:
        """The messages of a chat-endpoint form, rebuilt as the form builds them (``form.request``):
        the prompt, or after an unusable answer the prompt, that answer's final text and the
        correction (or prompt and correction in one user turn). Every message is compared with its
        rebuilt text and what differs is read; messages in any other arrangement are read whole.
        Returns the candidates the prompt shows."""
        if not isinstance(value, list):
            self.free(value, "messages that are not a list", f"{req.where}, messages")
            return []
        sent: list[tuple[int, object, str]] = []  # (position, role, text) of every readable message
        for i, m in enumerate(value):
            at = f"{req.where}, message {i + 1}"
            if not isinstance(m, dict):
                self.free(m, "a message that is not an object", at)
                continue
            role, content = m.get("role"), m.get("content")
            for k, v in m.items():
                if k not in ("role", "content"):
                    self.free(v, f"message field {k}, which the client never sends", at)
            if isinstance(content, list):
                self.finding("unverified", "request", "message content sent as a list of parts (the client sends strings)", at)
                content = message_text(content)
            elif not isinstance(content, str):
                self.free(content, "message content that is not a string", at)
                continue
            sent.append((i, role, content))
        want, repeated = self._turns(form, req)
        if want is None or len(sent) != len(value) or [r for _, r, _ in sent] != [m["role"] for m in want]:
            return self._unexpected_turns(sent, req, form, want is None)
        shown: list[Candidate | None] = []
        for (i, _, text), message in zip(sent, want, strict=True):
            at = f"{req.where}, message {i + 1}"
            if rc.PROMPT_MARK in message["content"]:
                before, after = message["content"].split(rc.PROMPT_MARK)
                shown = self.prompt(text, req, form, before, after)
            elif message["role"] == "assistant":
                self.spans(message["content"], text, [], at, "an assistant turn that is not the provider's own final text")
            else:
                self.spans(message["content"], text, [], at, "text the correction template does not produce")
        if repeated is not None:
            finish, _ = rc.response_facts(repeated.get("response"))
            entries = [self.rebuilt.entry(c) for c in shown if c is not None]
            verdict = form.judge(repeated.get("content"), repeated.get("reasoning"), self.ctx, entries, finish_reason=finish)
            if verdict.error != "repeats_history":
                self.finding("unverified", "request", "a correction after an answer the client takes (it repeats no policy "
                             "of the history shown)", req.where)
        return shown

    def _turns(self, form: PromptForm, req: Request) -> tuple[list[Mapping[str, str]] | None, dict[str, Any] | None]:
        """The messages ``form`` sends at this call, with ``rc.PROMPT_MARK`` where the prompt goes:
        the prompt, or after the recorded answer of the previous attempt the correction with the fault
        ``form.read`` finds in it, or ``REPEATS_HISTORY`` when it holds a proposal (then that answer
        is returned too: the correction is the client's only if it repeats the history shown, which
        the caller checks once it knows the history). None when that answer is not recorded."""
        previous = self.answered.get((req.iteration, req.attempt - 1)) if req.attempt > 0 else None
        if req.attempt > 0 and previous is None:
            return None, None
        detail, repeated = "", None
        if previous is not None:
            finish, _ = rc.response_facts(previous.get("response"))
            result = form.read(previous.get("content"), self.task.D, reasoning=previous.get("reasoning"), finish_reason=finish)
            detail, repeated = (REPEATS_HISTORY, previous) if result.ok else (result.detail, None)
        req_form = form.request(rc.PROMPT_MARK, ctx=self.ctx, shown=[], iteration=req.iteration, attempt=req.attempt,
                                previous=None if previous is None else previous.get("content"), detail=detail)
        return list(req_form.messages or ()), repeated

    def _unexpected_turns(self, sent: list[tuple[int, object, str]], req: Request, form: PromptForm,
                          unknown: bool) -> list[Candidate | None]:
        """Messages not in the form's arrangement: the first user message is read as the prompt,
        every other message whole, numbers and all."""
        if unknown:
            self.finding("unverified", "request", "a correction after an answer that is not recorded", req.where)
        prompt_seen = False
        shown: list[Candidate | None] = []
        for i, role, text in sent:
            if role == "user" and not prompt_seen:
                prompt_seen = True
                shown = self.prompt(text, req, form)
            else:
                self.free(text, f"a {role} message at position {i + 1}, which the client does not send there",
                          f"{req.where}, message {i + 1}")
        return shown

    def prompt(self, text: str, req: Request, form: PromptForm, before: str = "", after: str = "") -> list[Candidate | None]:
        """A prompt of ``form`` (the chat prompt in a message, or a document), with ``before``/``after``
        what the client puts around it in the same message: each history entry the form prints
        matched and checked (``entry``), each number the form derives from them checked
        (``form.derived``), the rest read as prose, and the whole rebuilt from the shown candidates
        (``reconstruct.prompt_spans``). R2PO's critic prompt is checked by ``critic``. Returns the
        candidates shown (None for an entry that matches none)."""
        if form is CRITIC:
            self.critic(text, req, before, after)
            return []
        inner = text[len(before):len(text) - len(after)] if text.startswith(before) and text.endswith(after) \
            and len(text) >= len(before) + len(after) else text
        # the entries ``parse_request`` read in the same text with the same form, else read here
        entries = list(req.entries) if text == req.text and form.name == req.form else form.entries(text)
        shown: list[Candidate | None] = []
        flagged: list[tuple[int, int]] = []
        for k, e in enumerate(entries):
            before_count = self._problems
            c = self.entry(req, k, e)
            shown.append(c)
            if c is None or self._problems > before_count:
                flagged.append((e.start, e.end))
        rebuilt = self._rebuilt_for(form)
        verified = [rebuilt.entry(c) for c in shown if c is not None] if all(c is not None for c in shown) else []
        skips = []
        for d in form.derived(text, verified):
            parsed = token_value(d.token) if d.token else None
            if d.value is not None and parsed is not None and renders(d.value, *parsed):
                skips.append(d.offset)  # derived from the shown encoded values, as the form computes it
            else:
                self.finding("unverified", d.kind, d.detail, f"{req.where}, prose at character {d.offset}" if d.token else req.where)
        self.prose(req, inner, entries if inner == text else form.entries(inner), skips)
        for a, b in rc.prompt_spans(rebuilt, text, entries, shown, before, after):
            if any(s <= a and b <= e for s, e in flagged) or any(a <= at < b for at in skips):
                continue  # inside an entry already reported, or a derived number checked above
            self.free(text[a:b], f"text the {form.name} form's templates do not produce: {text[a:b][:60]!r}", f"{req.where}, character {a}")
        return shown

    def critic(self, text: str, req: Request, before: str = "", after: str = "") -> None:
        printed = rc.critic_params(text)
        c = None
        if printed is not None:
            toks = [token_value(t) for t in printed.strip("[]").split(",")]
            if toks and all(t is not None for t in toks):
                vals = np.array([t[0] for t in toks if t])
                tols = np.array([t[1] for t in toks if t])
                idx, _ = self.match(vals, tols)
                c = self.cands[idx] if idx is not None else None
        if c is None:
            self.free(text, "a critic prompt whose candidate matches no evaluated candidate", req.where)
            return
        self.shown[c.index] = c
        self.finding("leak", "raw_trajectory", "raw states and the actions taken in them (R2PO's critic evidence)"
                     + ("" if not self.mech.encode_params else "; beside encoded parameters, a least-squares fit gives A"),
                     req.where, by_design=not (self.mech.encode_params or self.mech.scale_rewards))
        self.spans(before + rc.expected_critic(self.ctx, c, text) + after, text, [], req.where)

    def spans(self, expected: str, text: str, flagged: list[tuple[int, int]], where: str,
              what: str = "text the prompt templates do not produce") -> None:
        """Read every stretch of ``text`` that the client does not produce (``expected``)."""
        for a, b in rc.differing_spans(expected, text):
            if any(s - 2 <= a and b <= e + 2 for s, e in flagged):
                continue  # inside an entry already reported
            self.free(text[a:b], f"{what}: {text[a:b][:60]!r}", f"{where}, character {a}")

    # -- anything the client's code would not have sent ---------------------------------------------
    def free(self, value: object, why: str, where: str) -> None:
        """Read every number in a value (any precision, integers too) against every raw value; what
        is not raw is unverified (``why``), unless ``why`` is empty."""
        hits = self.raw_hits(value)
        for kind, label in hits:
            self.finding("leak", kind, f"raw {label} where the client sends none", where)
        if not hits and why:
            self.finding("unverified", "request", why, where)

    def raw_hits(self, value: object) -> list[tuple[str, str]]:
        tokens: list[str] = []
        _numbers(value, tokens)
        out: list[tuple[str, str]] = []
        for tok in tokens:
            parsed = token_value(tok)
            if parsed is None or parsed[0] == 0:
                continue
            v, tol = parsed
            hit = self._raw_match(v, tol)
            if hit is not None and hit not in out:
                out.append(hit)
        return out

    def _raw_match(self, v: float, tol: float) -> tuple[str, str] | None:
        opt = self.task.optimal_return
        if opt is not None and not (self.mech.disclose_optimum or self.mech.disclose_reward_structure) and renders(opt, v, tol):
            return "optimum", "optimal return"
        for c in self.cands:
            if c.ret != 0 and renders(c.ret, v, tol) and (not self.mech.scale_rewards or not renders(c.feedback_enc.ret, v, tol)):
                return "raw_return", "return"
            for k, x in c.feedback.components.items():
                if x != 0 and renders(x, v, tol) and not renders(c.feedback_enc.components.get(k, math.nan), v, tol):
                    return "raw_component", f"component {k}"
        if tol < 0.5 or self.mech.encode_params:  # integers collide with small raw parameters too often unless encoded
            P = self.raw
            hit = (np.abs(P - v) <= tol * (1 + 1e-9) + 1e-12) & (np.abs(P) >= 10 * tol) & ~(np.abs(self.enc - v) <= tol + 1e-12)
            if hit.any():
                return "raw_param", "parameter"
        return None

    def run(self) -> AuditReport:
        for row, req in zip(self.calls, self.requests, strict=True):  # in the order sent: the client's state follows it
            self.report.requests += 1
            if not row.get("answered", True):
                self.report.unanswered.append(int(row["id"]))
            self.body(row, req)
        if self.replay.changes != self.adaptations:
            self.finding("unverified", "request", "the run's recorded endpoint adaptations are not the ones its recorded "
                         f"exchanges lead to ({len(self.adaptations)} recorded, {len(self.replay.changes)} replayed)",
                         "llm_adaptations")
        self.channels()
        self.anchors()
        self.timing()
        self.identifiers()
        if self.attacks:
            self.exposure()
        order = {"leak": 0, "identifier": 1, "unverified": 2, "exposed": 3, "channel": 4}
        self.report.findings.sort(key=lambda f: order.get(f.severity, 3))
        return self.report

    def exposure(self) -> None:
        """Run and score every attack (``exposure.assess``): exposures, attacks not run, the
        public-dynamics line and the run seed read off the transcript."""
        if not self.requests or not (self.mech.encode_params or self.mech.scale_rewards):
            return
        if self.simulate:
            self.report.sim_bound = self.limits.describe()
        found = assess(self.requests, self.task, self.config.box, self.mech, self.cands, self.secrets, limits=self.limits,
                       simulate=self.simulate, grid=run_grid_factor(self.config, self.secrets))
        for x in found.exposures:
            if x.target == "c":
                secret = "c"
            elif x.target == "a":
                secret = f"a_j on {x.coords} of {self.task.D} coordinates"
            elif x.target == "raw params":
                secret = "the best shown policy's raw parameters (largest error as a share of the box width)"
            else:
                secret = f"the best shown policy's {x.target}"
            self.finding("exposed", x.attack, f"recovers {secret} to {100 * x.error:.2g}%: {x.detail}", "transcript",
                         by_design=x.paper)
        self.report.not_run = found.not_run
        self.report.near_misses += found.near_misses
        self.report.estimates = found.estimates
        if found.note:
            self.report.notes.append(found.note)
        self.report.public_dynamics = self._public_dynamics(found)
        self._seed_channel(found)

    def _public_dynamics(self, found: Assessment) -> str:
        """The line for a task whose env the provider can build: what the simulator fits got here."""
        if not self.mech.encode_params or not env_is_public(self.task):
            return ""
        got = []
        for x in found.exposures:
            if x.attack.startswith("sim-"):
                got.append(f"{x.attack}: {x.target} within {100 * x.error:.2g}%")
        for o in found.simulated:
            if o.error is not None and not any(g.startswith(f"{o.attack}: {o.target} ") for g in got):
                got.append(f"{o.attack}: {o.target} within {100 * o.error:.3g}% (prior {100 * (o.prior_error or 0):.3g}%)")
        ran = "; here " + ", ".join(got) if got else ""
        return (f"task {self.task.name} runs the public env {self.task.env_id}, so the provider can simulate it: the encodings "
                f"protect the secrets only as far as the shown history leaves them undetermined, whatever the preset "
                f"(docs/threat-model.md, 'What the encoding cannot hide'){ran}")

    def _seed_channel(self, found: Assessment) -> None:
        """The run seed read off the transcript (any preset that encodes parameters): it replays the warm-up
        draws and gives every episode's initial state."""
        if not self.mech.encode_params or not self.requests:
            return
        v = view_of(self.requests, self.task, self.config.box)
        seed, how = find_run_seed(v)
        if seed is not None:
            self.finding("channel", "run_seed", f"the run seed is read off the transcript ({how}): it gives every episode's "
                         "initial state (seeding.episode_seeds) and the warm-up draws", "transcript")

    # -- the user's own names --------------------------------------------------------------------
    def identifiers(self) -> None:
        """Names of the task's own env (its module, class, file and folder names, from the stored
        declaration) must not reach a prompt under a preset that encodes parameters."""
        if not self.mech.encode_params or env_is_public(self.task):
            return
        names = env_identifiers(self.task)
        if not names:
            return
        for req in self.requests:
            text = req.body or req.text
            for name in names:
                if re.search(rf"(?<![A-Za-z0-9_]){re.escape(name)}(?![A-Za-z0-9_])", text):
                    self.finding("identifier", "identifier", f"the name '{name}' of the task's own env ({names[name]})",
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


def _numbers(value: object, out: list[str]) -> None:
    """Every number in a JSON value as printed: JSON numbers, and number tokens inside strings."""
    if isinstance(value, bool) or value is None:
        return
    if isinstance(value, (int, float)):
        out.append(json.dumps(value))
    elif isinstance(value, str):
        out.extend(tok for _, tok in number_tokens(value))
    elif isinstance(value, dict):
        for k, v in value.items():
            _numbers(k, out)
            _numbers(v, out)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _numbers(v, out)


def _num(v: object) -> float:
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def run_grid_factor(config: RunConfig, secrets: Secrets | None) -> float:
    """The secret grid factor g of a run on the grid (``client.codec.grid_factor``), 1 off the grid or
    without its key file: attacks on a are scored against the effective scale g a_j."""
    if secrets is None or config.numbers != "grid":
        return 1.0
    from ..client.codec import grid_factor

    return grid_factor(secrets, config.box, config.mechanisms.warp_params)


def search_config(stored: dict[str, Any], run_dir: Path) -> RunConfig:
    """The configuration of a prompted search run.

    Raises:
        StoreError: not a prompted search run (an RL baseline).
        ConfigError: the stored configuration names a method or task this process does not know (a
            method from a plugin that is not installed here).
    """
    if "mechanisms" not in stored:
        raise StoreError(f"{run_dir} is not a prompted search run (no mechanisms in its configuration)")
    return RunConfig.from_json(stored)


def audit_run(run_dir: Path, *, limits: SimLimits | None = None, simulate: bool = True, attacks: bool = True) -> AuditReport:
    """Audit every recorded outgoing request of a run against the raw values in its store.

    Every field of every request body is read; attacks on the transcript are scored against the
    key file when it is in the run directory (else against the store, for pure scales). A key file
    that does not load is treated as absent. The simulator attacks run within ``limits`` (default
    ``simfit.DEFAULT_LIMITS``, stated in the report); ``simulate=False`` leaves them out (listed
    as not run). ``attacks=False`` runs none of the attacks, transcript or simulator (the quick
    audit after a run): every request is still read and accounted for, the run-level channels and
    identifiers still found; the report's ``attacked`` is false and its verdict never CLEAN.

    Raises:
        StoreError: ``run_dir`` is not a directory, holds no readable store, or is not a prompted
            search run (an RL baseline).
        ConfigError: its configuration names a method or task unknown here (``search_config``).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    with open_run(run_dir) as run:
        store = run.store
        config = search_config(run.stored, run_dir)
        candidates = store.candidates()
        calls = store.llm_calls()
        sessions, changes, adaptations = store.llm_sessions(), store.endpoint_changes(), store.llm_adaptations()
        keyed = store.streams_keyed()
        created = {t[0]: t[3] for t in store.candidate_times()}
        secrets = run.load_secrets(optional=True)  # a key file that does not load counts as absent
        key_state = "" if secrets is not None else ("missing" if not run.key_path.exists() else "unusable (damaged, or another run's)")
    told = [(created[c.index], c) for c in candidates if c.index in created]
    report = _Auditor(run_dir, config, candidates, calls, secrets, sessions=sessions, endpoint_changes=changes,
                      adaptations=adaptations, limits=limits, simulate=simulate, keyed_streams=keyed, attacks=attacks,
                      told=told).run()
    if key_state:  # the audit reads what was sent without the key; say what that leaves unverified
        report.notes.append(f"the key file {run.key_path} is {key_state}: what was sent is checked without the secrets, "
                            "so the requests' sampling seeds are not verified, and the attacks are scored from the stored values "
                            "where the run's maps allow it")
    return report
