"""``ppprops audit DIR``: does any recorded request hold a raw value the preset promises to hide?

How it decides (docs/privacy.md, "The audit"): each history entry of each request is matched to
the candidate it shows through its printed parameters, then every printed field is compared with
the raw and the encoded value of the same quantity, at the precision it was printed with (any
number of decimals, trailing zeros dropped, exponent form, integers):

- printed value = raw value, but not the encoded one: a **leak** (raw value sent);
- printed value = raw value = encoded value (zero, or a factor that rounds to 1): a coincidence,
  counted, not a leak, since the provider cannot tell it apart from any encoded value;
- printed value = encoded value only: as designed;
- neither: **unverified** (the audit cannot account for what was sent).
Fields a preset sends raw by design (vanilla, df) are leaks too, marked "by design". The prose
around the history is searched for the optimal return at every rendering and for raw returns and
components printed with at least two decimals. Known side channels of the scheme (a diagnostic
that equals or determines the raw return, clipped candidates at the box edge, warm-up spread,
the run seed, integer-return lattices, known caps) are reported as **channels**.

Exit code: 0 when nothing leaked and everything was verified (channels are warnings), 1 with
the locations otherwise; ``--strict`` also fails on channels.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import seeding
from ..config import RunConfig
from ..errors import StoreError
from ..methods import Mechanisms
from ..store import Candidate, open_store
from ..wire.document import document_target
from ..wire.encoded import EncodedEntry
from ..wire.transcript import ShownEntry, number_tokens, open_target, outside_entries
from .knowledge import facts_for
from .transcript import Request, load_requests

_TOKEN = re.compile(r"([-+]?)(\d*)(?:\.(\d*))?(?:[eE]([-+]?\d+))?")
MAX_LOCATIONS = 5  # locations listed per finding; the count covers all


def token_value(tok: str) -> tuple[float, float] | None:
    """A printed number and half its last printed digit (how far the value it renders may lie)."""
    m = _TOKEN.fullmatch(tok.strip())
    if m is None or not (m.group(2) or m.group(3)):
        return None
    decimals = len(m.group(3) or "")
    exponent = int(m.group(4) or 0)
    return float(tok), 0.5 * 10.0 ** (exponent - decimals)


def renders(value: float, printed: float, tol: float) -> bool:
    """Could ``value`` be printed as ``printed`` at that precision (rounding, either tie rule)?"""
    return abs(value - printed) <= tol * (1 + 1e-9) + 1e-12 * max(1.0, abs(value))


@dataclass
class Finding:
    """One kind of problem in one field, with where it was seen (first few places) and how often."""

    severity: str  # leak | unverified | channel
    kind: str
    detail: str
    by_design: bool = False
    locations: list[str] = field(default_factory=list)
    count: int = 0

    def add(self, where: str) -> None:
        self.count += 1
        if len(self.locations) < MAX_LOCATIONS:
            self.locations.append(where)

    def to_json(self) -> dict[str, Any]:
        return {"severity": self.severity, "kind": self.kind, "detail": self.detail, "by_design": self.by_design,
                "count": self.count, "locations": self.locations}


@dataclass
class AuditReport:
    run_dir: str
    method: str
    mechanisms: dict[str, bool]
    requests: int = 0
    entries: int = 0
    checked: dict[str, int] = field(default_factory=lambda: {"params": 0, "return": 0, "components": 0, "diagnostics": 0})
    coincidences: int = 0
    findings: list[Finding] = field(default_factory=list)

    def _of(self, severity: str) -> list[Finding]:
        return [f for f in self.findings if f.severity == severity]

    @property
    def leaks(self) -> list[Finding]:
        return self._of("leak")

    @property
    def unverified(self) -> list[Finding]:
        return self._of("unverified")

    @property
    def channels(self) -> list[Finding]:
        return self._of("channel")

    @property
    def clean(self) -> bool:
        return not self.leaks and not self.unverified

    def exit_code(self, strict: bool = False) -> int:
        return 0 if self.clean and not (strict and self.channels) else 1

    def verdict(self, strict: bool = False) -> str:
        if self.leaks:
            design = all(f.by_design for f in self.leaks)
            kinds = ", ".join(sorted({f.kind for f in self.leaks}))
            why = f" (by design of preset {self.method})" if design else ""
            return f"LEAK: raw values were sent{why}: {kinds}"
        if self.unverified:
            return f"UNVERIFIED: {sum(f.count for f in self.unverified)} printed value(s) match neither the raw nor the encoded value"
        n = len(self.channels)
        tail = f"; {n} known channel(s) remain (warnings)" if n else ""
        if strict and n:
            return f"CHANNELS (strict): no raw value was sent, but {n} known channel(s) remain"
        return f"CLEAN: no raw parameter, return, reward component or optimal return was sent{tail}"

    def to_json(self, strict: bool = False) -> dict[str, Any]:
        return {"run_dir": self.run_dir, "method": self.method, "mechanisms": self.mechanisms, "requests": self.requests,
                "entries": self.entries, "checked": self.checked, "coincidences": self.coincidences,
                "verdict": self.verdict(strict), "exit_code": self.exit_code(strict),
                "findings": [f.to_json() for f in self.findings]}

    def format(self, strict: bool = False) -> str:
        c = self.checked
        lines = [
            f"audit of {self.run_dir} (method {self.method}): {self.requests} requests, {self.entries} history entries; "
            f"checked {c['params']} parameters, {c['return']} returns, {c['components']} components, {c['diagnostics']} diagnostics "
            f"({self.coincidences} coincidental equalities of raw and encoded values)",
            f"verdict: {self.verdict(strict)}",
        ]
        for f in self.findings:
            tag = f"{f.severity}{' (by design)' if f.by_design else ''}"
            where = "; ".join(f.locations) + (" ..." if f.count > len(f.locations) else "")
            lines.append(f"  {tag:<18} {f.kind:<22} {f.detail} [{f.count}x: {where}]")
        return "\n".join(lines)


class _Auditor:
    def __init__(self, run_dir: Path, config: RunConfig, candidates: Sequence[Candidate], requests: Sequence[Request]) -> None:
        self.config = config
        self.mech: Mechanisms = config.mechanisms
        self.task = config.make_task()
        self.cands = list(candidates)
        self.requests = list(requests)
        self.report = AuditReport(str(run_dir), config.method, self.mech.to_json())
        self._findings: dict[tuple[str, str, str], Finding] = {}
        self.enc = np.array([c.params_enc for c in self.cands], dtype=np.float64).reshape(len(self.cands), -1)
        self.raw = np.array([c.params for c in self.cands], dtype=np.float64).reshape(len(self.cands), -1)
        self.shown: dict[int, Candidate] = {}  # candidates that appeared in some request

    def finding(self, severity: str, kind: str, detail: str, where: str, *, by_design: bool = False) -> None:
        key = (severity, kind, detail)
        if key not in self._findings:
            self._findings[key] = Finding(severity, kind, detail, by_design)
            self.report.findings.append(self._findings[key])
        self._findings[key].add(where)

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
    def match(self, vals: np.ndarray, tols: np.ndarray, ret_tok: str) -> tuple[int | None, str]:
        if not self.cands or vals.shape[0] != self.enc.shape[1]:
            return None, ""
        need = math.ceil(vals.shape[0] / 2)
        for name, matrix in (("encoded", self.enc), ("raw", self.raw)):
            score = np.sum(np.abs(matrix - vals) <= tols * (1 + 1e-9) + 1e-12, axis=1)
            best = int(score.max())
            if best < need:
                continue
            tied = [i for i in np.flatnonzero(score == best)]
            rv = token_value(ret_tok)
            for i in tied:  # among equal params (a repeated policy), the one whose return was printed
                c = self.cands[i]
                if rv is not None and (renders(c.feedback_enc.ret, *rv) or renders(c.ret, *rv)):
                    return int(i), name
            return int(tied[0]), name
        return None, ""

    def entry(self, req: Request, k: int, e: ShownEntry) -> Candidate | None:
        """Check one shown entry; returns the candidate it shows, or None if it matches none."""
        where = f"{req.where}, entry {k + 1}"
        parsed = [token_value(t) for t in e.params]
        if any(p is None for p in parsed):
            self.finding("unverified", "entry", "history entry with unreadable parameters", where)
            return None
        vals = np.array([p[0] for p in parsed if p is not None])
        tols = np.array([p[1] for p in parsed if p is not None])
        idx, how = self.match(vals, tols, e.ret)
        if idx is None:
            self.finding("unverified", "entry", "history entry that matches no evaluated candidate", where)
            return None
        c = self.cands[idx]
        self.shown[c.index] = c
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
            parsed_d = token_value(tok)
            if parsed_d is None:
                continue
            self.report.checked["diagnostics"] += 1
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
    def target(self, req: Request, shown: list[Candidate | None]) -> int | None:
        """The document form's open block: its return must be ``wire.document.document_target`` of
        the shown candidates' encoded returns (a derived encoded value). Returns its offset when
        it is, so the prose check skips it; otherwise it is unverified and read like any prose."""
        found = open_target(req.text)
        if found is None:
            if req.form == "document":
                self.finding("unverified", "target", "a document prompt that does not end in an open block", req.where)
            return None
        at, tok = found
        parsed = token_value(tok)
        entries = [EncodedEntry(index=c.index, params=(), ret=float(c.feedback_enc.ret)) for c in shown if c is not None]
        if parsed is not None and entries and len(entries) == len(shown) and renders(document_target(entries), *parsed):
            return at
        self.finding("unverified", "target", "the open block's return is not the target computed from the shown "
                     "encoded returns", f"{req.where}, prose at character {at}")
        return None

    def prose(self, req: Request, skip: int | None = None) -> None:
        optimum = self.task.optimal_return
        by_design = self.mech.disclose_optimum or self.mech.disclose_reward_structure
        raw_rewards = [(c.index, "return", c.ret) for c in self.cands]
        raw_rewards += [(c.index, f"component {k}", v) for c in self.cands for k, v in c.feedback.components.items()]
        for offset, text in outside_entries(req.text, list(req.entries)):
            for pos, tok in number_tokens(text):
                if skip is not None and offset + pos == skip:
                    continue  # the document's target, checked by ``target``
                parsed = token_value(tok)
                if parsed is None:
                    continue
                v, tol = parsed
                where = f"{req.where}, prose at character {offset + pos}"
                if optimum is not None and renders(optimum, v, tol) and abs(optimum) >= 1:
                    self.finding("leak", "optimum", f"the optimal return {optimum:g} (printed {tok})", where, by_design=by_design)
                if "." in tok and len(tok.split(".")[1].split("e")[0].split("E")[0]) >= 2:
                    for idx, label, raw in raw_rewards:
                        if abs(raw) >= 0.01 and renders(raw, v, tol):
                            self.finding("leak", "raw_return" if label == "return" else "raw_component",
                                         f"raw {label} of candidate {idx} in the prose", where, by_design=not self.mech.scale_rewards)
                            break

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
        if mech.encode_params and not mech.encoded_warmup:
            for r in self.requests:
                if r.seed is not None and r.seed == seeding.llm_seed(self.config.seed, r.iteration, r.attempt):
                    self.finding("channel", "run_seed", "the request's sampling seed derives from the run seed; a provider that "
                                 "finds a small seed can replay the raw warm-up", r.where)
        rets = [c.ret for c in shown]
        if mech.scale_rewards and not mech.warp_rewards and len(set(rets)) >= 3:
            if facts_for(self.task.name).integer_returns or all(float(r).is_integer() for r in rets):
                self.finding("channel", "reward_lattice", "integer returns scaled by c keep a lattice: the gcd of differences of "
                             "printed returns gives c", f"{len(set(rets))} distinct returns shown")
        if mech.scale_rewards and not mech.warp_rewards and not mech.secret_offsets:
            caps = {v for _, v, _, _ in facts_for(self.task.name).caps}
            if self.task.optimal_return is not None:
                caps.add(float(self.task.optimal_return))
            for c in shown:
                if c.ret in caps and c.ret != 0:
                    self.finding("channel", "known_cap", f"a return at the public cap {c.ret:g} gives c = printed / {c.ret:g}",
                                 f"candidate {c.index}")

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

    def run(self) -> AuditReport:
        for req in self.requests:
            self.report.requests += 1
            shown = [self.entry(req, k, e) for k, e in enumerate(req.entries)]
            skip = self.target(req, shown) if req.form == "document" else None
            self.prose(req, skip)
        self.channels()
        order = {"leak": 0, "unverified": 1, "channel": 2}
        self.report.findings.sort(key=lambda f: order.get(f.severity, 3))
        return self.report


def _num(v: object) -> float:
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def search_config(stored: dict[str, Any], run_dir: Path) -> RunConfig:
    """The configuration of a prompted search run; anything else (an RL baseline) is a StoreError."""
    if "mechanisms" not in stored:
        raise StoreError(f"{run_dir} is not a prompted search run (no mechanisms in its configuration)")
    return RunConfig.from_json(stored)


def audit_run(run_dir: Path) -> AuditReport:
    """Audit every recorded outgoing request of a run against the raw values in its store."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise StoreError(f"{run_dir} is not a directory")
    store = open_store(run_dir)
    try:
        config = search_config(store.config(), run_dir)
        candidates = store.candidates()
    finally:
        store.close()
    return _Auditor(run_dir, config, candidates, load_requests(run_dir)).run()
