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

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..client.secrets import Secrets
from ..config import RunConfig
from ..errors import StoreError
from ..methods import Mechanisms
from ..rundir import open_run
from ..store import Candidate
from ..wire.transcript import ShownEntry, number_tokens, outside_entries
from . import reconstruct as rc
from . import run_checks, simfit
from .request_body import SENT_FIELDS as SENT_FIELDS  # re-exported: the fields the client may send
from .request_body import BodyReader
from .requests import Request, parse_request
from .run_checks import IGNORED_NAMES as IGNORED_NAMES  # re-exported, with the two below: their home was here
from .run_checks import env_identifiers as env_identifiers
from .run_checks import run_grid_factor as run_grid_factor
from .simfit import SimLimits
from .tokens import renders, token_value
from .view import Estimate

MAX_LOCATIONS = 5  # locations listed per finding; the count covers all
TIMING_KINDS = ("request-timing", "request_timing")  # the clock exposed (its calibration gives the best raw return), and as a channel
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
    """One audit of one run: what it has read so far, its checks of printed values, and its findings.

    ``run`` reads every call's body in the order sent (``request_body.BodyReader``, which hands the
    history entries and any text the client would not produce back to ``entry``, ``free`` and
    ``spans``), then runs the run-level checks (``run_checks``) and sorts the findings.
    """

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
        self.problems = 0  # occurrences of findings other than channels so far (``BodyReader.prompt`` flags the entries that add some)
        self.bodies = BodyReader(self)  # reads each call's body; its prompt contexts are built here, once per form
        self.replay = rc.ClientReplay(config.llm, self.task.D, sessions, endpoint_changes)
        self.adaptations = [str(a.get("change")) for a in adaptations]
        self.report = AuditReport(str(run_dir), config.method, self.mech.to_json(), attacked=attacks)
        self._findings: dict[tuple[str, str, str], Finding] = {}
        D = self.task.D  # (N, D) even when nothing was evaluated yet (N = 0: a new study, a run stopped at its first reset)
        self.enc = np.array([c.params_enc for c in self.cands], dtype=np.float64).reshape(len(self.cands), D)
        self.raw = np.array([c.params for c in self.cands], dtype=np.float64).reshape(len(self.cands), D)
        self.shown: dict[int, Candidate] = {}  # candidates that appeared in some request
        self.shown_diagnostics: dict[int, dict[str, str]] = {}  # candidate -> each diagnostic as some request printed it

    def finding(self, severity: str, kind: str, detail: str, where: str, *, by_design: bool = False) -> None:
        key = (severity, kind, detail)
        if key not in self._findings:
            self._findings[key] = Finding(severity, kind, detail, by_design)
            self.report.findings.append(self._findings[key])
        self._findings[key].add(where)
        if severity != "channel":
            self.problems += 1

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
            self.bodies.body(row, req)
        if self.replay.changes != self.adaptations:
            self.finding("unverified", "request", "the run's recorded endpoint adaptations are not the ones its recorded "
                         f"exchanges lead to ({len(self.adaptations)} recorded, {len(self.replay.changes)} replayed)",
                         "llm_adaptations")
        run_checks.channels(self)
        run_checks.anchors(self)
        run_checks.timing(self)
        run_checks.stop(self)
        run_checks.identifiers(self)
        if self.attacks:
            run_checks.exposure(self)
        order = {"leak": 0, "identifier": 1, "unverified": 2, "exposed": 3, "channel": 4}
        self.report.findings.sort(key=lambda f: order.get(f.severity, 3))
        return self.report


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
