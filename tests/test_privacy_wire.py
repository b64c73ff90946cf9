"""For pp, the bytes sent over HTTP hold no raw parameter, raw return or optimal return.

A recording proxy (the fault server with no faults, ``record`` on, passing every request to the
upstream) sits between ppprops and the embedded llama.cpp server and keeps every byte sent. The
check reads those bytes the way the prompt writes values (the history's params arrays, return
lines and reward components, at the prompt's precision and as integers) and compares them with
the raw values recorded on the client. Secrets are fixed here so the check is deterministic; the
same check must flag a vanilla run, which sends raw values by design.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ppprops.client.hardening import generate_secrets
from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig
from ppprops.llm.embedded import MODEL_ALIAS
from ppprops.privacy.audit import audit_run
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.tasks import get_task
from ppprops.testing.fault_server import FaultConfig, FaultServer

from support import make_config

pytestmark = pytest.mark.llm

HARDENED_SECRETS_SEED = 154  # the run id is fixed too (privacy-pp-hardened); see _proxied_run
ENTRY = re.compile(r"params: \[([^\]]*)\]\nreturn: (\S+)(?:\ncomponents: ([^\n]*))?")


def _renderings(x: float, decimals: int) -> set[str]:
    """The ways a prompt could write x: at 0..decimals+2 decimals, and as an integer."""
    out = {f"{x:.{d}f}" for d in range(decimals + 3)}
    if float(x).is_integer():
        out.add(str(int(x)))
    return {s[1:] if s.startswith("-") and float(s) == 0 else s for s in out}


NUMBER = re.compile(r"-?\d*(?:\.(\d*))?(?:[eE]([+-]?\d+))?")
COMPONENT = re.compile(r"([^\s=,]+)=([^\s,]+)")


def _prints(x: float, tok: str) -> bool:
    """Could x be printed as the number ``tok``, rounded at tok's own precision (the prompt writes
    encoded params to a few significant digits, not to a fixed number of decimals)?"""
    m = NUMBER.fullmatch(tok.strip())
    if m is None:
        return False
    half = 0.5 * 10.0 ** (int(m.group(2) or 0) - len(m.group(1) or ""))
    return abs(float(x) - float(tok)) <= half * (1 + 1e-9)


def leaks(requests: list[bytes], run_dir: Path, optimum: float | None) -> list[str]:
    """What the requests print raw: a candidate's raw params, return or component in its history
    entry, and the optimal return anywhere but where a shown entry prints its own encoded value
    (an encoded value may print as the optimum by chance; the raw value in its place is a leak)."""
    store = open_store(run_dir)
    cands = store.candidates()
    decimals = int(store.config()["decimals"])
    store.close()
    found: list[str] = []
    for raw in requests:
        body = raw.split(b"\r\n\r\n", 1)[1]
        if not body:
            continue
        text = "\n".join(m["content"] for m in json.loads(body)["messages"])
        encoded: list[tuple[int, int]] = []  # spans that print a shown candidate's own encoded values
        for m in ENTRY.finditer(text):
            tokens = m.group(1).split(",")
            shown = [float(v) for v in tokens]
            own = [c for c in cands if _same_entry(c, tokens)]  # the candidates this entry shows
            if own:
                encoded.append(m.span(1))
                if any(_prints(c.feedback_enc.ret, m.group(2)) for c in own):
                    encoded.append(m.span(2))
                for comp in COMPONENT.finditer(m.group(3) or ""):
                    if any(_prints(c.feedback_enc.components.get(comp.group(1), math.nan), comp.group(2)) for c in own):
                        encoded.append((m.start(3) + comp.start(2), m.start(3) + comp.end(2)))
            for c in cands:
                # zero maps to zero under any diagonal scaling (the scheme keeps signs and zeros
                # by design), so only nonzero coordinates can reveal a magnitude
                nonzero = [(p, s) for p, s in zip(c.params, shown) if float(f"{p:.{decimals}f}") != 0.0]
                same = sum(f"{p:.{decimals}f}" == f"{s:.{decimals}f}" for p, s in nonzero)
                if nonzero and same > len(nonzero) // 2:
                    found.append(f"raw params of candidate {c.index}")
            for c in own:
                if any(m.group(2) == r for r in _renderings(c.ret, decimals)):
                    found.append(f"raw return of candidate {c.index}")
                for k, v in c.feedback.components.items():
                    if m.group(3) and re.search(rf"\b{re.escape(k)}=({'|'.join(map(re.escape, _renderings(v, decimals)))})\b", m.group(3)):
                        found.append(f"raw component {k} of candidate {c.index}")
        if optimum is not None:
            for r in _renderings(optimum, decimals):
                # the episode_length diagnostic is the one known channel that can print this number
                hits = [h for h in re.finditer(rf"(?<![\w.]){re.escape(r)}(?![\w.])", text)
                        if not text[: h.start()].endswith("episode_length=")
                        and not any(a <= h.start() and h.end() <= b for a, b in encoded)]
                if hits:
                    found.append(f"optimal return {r}")
            if "optimal return" in text:
                found.append("optimal return stated")
    return found


def _same_entry(c, tokens: list[str]) -> bool:  # type: ignore[no-untyped-def]
    """The entry's printed params are candidate c's encoded ones."""
    return len(tokens) == len(c.params_enc) and all(_prints(p, t) for p, t in zip(c.params_enc, tokens))


def _proxied_run(  # type: ignore[no-untyped-def]
    tmp_path: Path, embedded_server, method: str, task: str, iterations: int = 5, warmup: int = 6, **settings
) -> tuple[list[bytes], Path]:
    t = get_task(task)
    rng = np.random.default_rng(11)
    with FaultServer(FaultConfig(fault_rate=0.0, upstream=embedded_server.base_url, record=True, max_seconds=3600)) as proxy:
        llm = LLMConfig(base_url=proxy.base_url, model=MODEL_ALIAS, structured="grammar")
        if method == "r2po":
            cfg = replace(make_config(task, "vanilla", warmup=warmup, iterations=iterations, final_episodes=0, llm=llm, **settings),
                          method="r2po")
        else:
            cfg = make_config(task, method, warmup=warmup, iterations=iterations, final_episodes=0, llm=llm, **settings)
        if method == "pp-hardened":
            # its own kind of secrets (offsets, warps), drawn by the routine every run uses, from a fixed seed: on fresh
            # ones an attack reads a value by chance now and then; on this draw no a_j is within 2% of what a proposal
            # repeated at an integer or at the warm-up's edge gives clip-edge, nor c of what a tie at the top gives known-cap
            secrets = generate_secrets(f"privacy-{method}", t, cfg.encoding, rng=np.random.default_rng(HARDENED_SECRETS_SEED))
        else:
            secrets = Secrets(run_id=f"privacy-{method}", a=rng.uniform(1.7, 4.3, t.D), c=3.7193)
        start(cfg, tmp_path / method, secrets=secrets)
        captured = proxy.received()
    return captured, tmp_path / method


@pytest.mark.parametrize("method", ["vanilla", "pe", "df", "pp", "pp-hardened", "r2po"])
def test_the_proxy_sees_exactly_the_requests_the_store_holds(tmp_path: Path, embedded_server, method: str) -> None:  # type: ignore[no-untyped-def]
    """Every LLM method, R2PO's critic and its context checks included: nothing leaves unrecorded."""
    extra = {"episodes": 2} if method == "r2po" else {}
    requests, run_dir = _proxied_run(tmp_path, embedded_server, method, "CartPole", iterations=2, warmup=3, **extra)
    assert len(requests) >= 2
    _recorded_is_what_was_sent(requests, run_dir)
    if method == "r2po":
        assert any(b"You are a critic" in r for r in requests)
        report = audit_run(run_dir)  # the critic's raw evidence is read and reported (raw by design of this baseline)
        assert any(f.kind == "raw_trajectory" and f.by_design for f in report.leaks), report.format()


def _recorded_is_what_was_sent(requests: list[bytes], run_dir: Path) -> None:
    """Every request that crossed the wire (any method, any path) is a recorded one, byte for byte, and
    the store holds no request that was not sent: the audit reads exactly what the provider received.
    The one exception is the endpoint probe before the run (``llm.probe``): first, once, a bodiless
    ``GET /v1/models`` whose headers name no value of the run."""
    store = open_store(run_dir)
    recorded = [c["request"] for c in store.llm_calls()]
    store.close()
    probe, requests = requests[0], requests[1:]
    head, body = probe.split(b"\r\n\r\n", 1)
    assert head.startswith(b"GET /v1/models ") and body == b"" and b"content-length" not in head.lower()
    assert not any(r.startswith(b"GET ") for r in requests)
    assert len(requests) == len(recorded) and all(r.startswith(b"POST /v1/chat/completions ") for r in requests)
    assert [r.split(b"\r\n\r\n", 1)[1] for r in requests] == [r.encode("utf-8") for r in recorded]


@pytest.mark.parametrize("task", ["CartPole", "Acrobot"])
def test_pp_sends_no_raw_value(tmp_path: Path, embedded_server, task: str) -> None:  # type: ignore[no-untyped-def]
    iterations = 5 if task == "CartPole" else 3  # Acrobot: 21 parameters to CartPole's 10, twice the answer
    requests, run_dir = _proxied_run(tmp_path, embedded_server, "pp", task, iterations=iterations)
    posts = [r for r in requests if r.startswith(b"POST")]
    assert len(posts) >= iterations
    assert sum(b"params: [" in r for r in posts) == len(posts)  # the check did read history entries
    assert leaks(posts, run_dir, get_task(task).optimal_return) == []
    _recorded_is_what_was_sent(requests, run_dir)
    report = audit_run(run_dir)  # no raw value was sent, but the paper's channels give c within 1%: the audit fails
    assert not report.leaks and not report.unverified and report.entries > 0, report.format()
    assert report.exit_code() == 1 and "diagnostic" in {f.kind for f in report.exposed}, report.format()
    if task == "CartPole":  # episode_length = the raw return, reported as a channel rather than ignored
        assert any(f.kind == "diagnostic_return" for f in report.channels)


def test_pp_hardened_sends_no_raw_value_and_no_known_channel(tmp_path: Path, embedded_server) -> None:  # type: ignore[no-untyped-def]
    requests, run_dir = _proxied_run(tmp_path, embedded_server, "pp-hardened", "CartPole", iterations=3)
    posts = [r for r in requests if r.startswith(b"POST")]
    assert leaks(posts, run_dir, 500.0) == []
    assert all(b"episode_length" not in r for r in posts)
    _recorded_is_what_was_sent(requests, run_dir)
    # the transcript's channels, strictly; the simulator attacks have their own tests (a run whose
    # model happens to find a policy at the cap of 500 is EXPOSED by them, which no encoding hides)
    report = audit_run(run_dir, simulate=False)
    assert report.exit_code(strict=True) == 0, report.format()


def test_the_check_flags_vanilla(tmp_path: Path, embedded_server) -> None:  # type: ignore[no-untyped-def]
    requests, run_dir = _proxied_run(tmp_path, embedded_server, "vanilla", "CartPole")
    found = leaks([r for r in requests if r.startswith(b"POST")], run_dir, 500.0)
    assert any(f.startswith("raw params") for f in found)
    assert any(f.startswith("raw return") for f in found)
    assert "optimal return stated" in found
    report = audit_run(run_dir)
    assert report.exit_code() == 1 and {"raw_param", "raw_return", "optimum"} <= {f.kind for f in report.leaks}
