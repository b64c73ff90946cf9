"""The audit a run prints about itself: quick by default (every request read, no attack), the
attacks with ``--audit full`` (the verdict of ``ppprops audit DIR``), none with ``--audit off``;
and the quick audit still catches a raw value planted in a recorded request."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_audit import shown_vector

from ppprops.cli import main
from ppprops.privacy import simfit
from ppprops.privacy.audit import AuditReport, audit_run
from ppprops.privacy.commands import self_audit_line
from ppprops.store import open_store

from support import find_call, offline_llm, tamper_call

RUN = ["--env", "CartPole", "--warmup", "4", "--iterations", "3", "--final-episodes", "0", "--select-top", "0", "--quiet"]
PAPER = "they usually find pp EXPOSED by design (pp-hardened closes its channels)."


@pytest.fixture(autouse=True)
def small_simulations(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulator attacks of the full audit within a small bound (tests/test_simulator_attacks.py covers them)."""
    monkeypatch.setattr(simfit, "DEFAULT_LIMITS", simfit.SimLimits(vector_steps=500_000, env_steps=2_000))


def _run(out: Path, capsys: pytest.CaptureFixture[str], *args: str) -> str:
    """``ppprops run`` offline; its last line on stdout."""
    with offline_llm():
        assert main(["run", *RUN, "--out", str(out), *args]) == 0
    return capsys.readouterr().out.strip().splitlines()[-1]


def _channels(report: AuditReport) -> str:
    kinds = sorted({f.kind for f in report.channels})
    return f" Known channels: {', '.join(kinds)}." if kinds else ""


def test_the_quick_line_says_what_it_checked_and_names_the_full_audit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "pp"
    line = _run(out, capsys, "--method", "pp")
    report = audit_run(out, attacks=False)
    assert not report.attacked and report.requests == 3 and report.clean and not report.exposed
    kinds = sorted({f.kind for f in report.channels})
    known = f"; known channels: {', '.join(kinds)}" if kinds else ""
    assert line == f"privacy audit: nothing raw was sent (quick check of 3 requests{known}). Attacks not run: 'ppprops audit {out}'; {PAPER}"
    assert len(line) <= 240 + len(str(out))  # short enough to read: no attack names, no percentages
    assert "CLEAN" not in line and f"'ppprops audit {out}'" in line
    # a preset that closes the paper's channels is not told it keeps them
    hard = tmp_path / "hard"
    line = _run(hard, capsys, "--method", "pp-hardened", "--seed", "987654")
    kinds = sorted({f.kind for f in audit_run(hard, attacks=False).channels})
    known = f"; known channels: {', '.join(kinds)}" if kinds else ""
    assert line == f"privacy audit: nothing raw was sent (quick check of 3 requests{known}). Attacks not run: 'ppprops audit {hard}'."


def test_the_quick_report_never_says_clean(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "hard"
    _run(out, capsys, "--method", "pp-hardened", "--seed", "987654")
    quick, full = audit_run(out, attacks=False), audit_run(out)
    assert full.attacked and full.verdict().startswith(("CLEAN", "EXPOSED"))  # EXPOSED only if a fit lands on fresh secrets
    assert quick.verdict().startswith("NOTHING RAW SENT:") and quick.verdict().endswith("the attacks on the transcript did not run")
    assert "CLEAN" not in quick.verdict()
    assert quick.to_json()["attacked"] is False and "attacks: not run" in quick.format()
    assert not quick.not_run and not quick.sim_bound and not quick.public_dynamics  # nothing of the attacks' is claimed
    # the transcript checks are the full audit's own
    assert (quick.requests, quick.entries, quick.checked, quick.coincidences) == (full.requests, full.entries, full.checked,
                                                                                 full.coincidences)


def test_audit_full_prints_the_verdict_of_ppprops_audit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "pp"
    line = _run(out, capsys, "--method", "pp", "--prompt-form", "chat", "--audit", "full")
    assert main(["audit", str(out)]) == 1  # pp: EXPOSED by the paper's channels (c = printed return / episode_length)
    verdict = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("verdict: "))[len("verdict: "):]
    assert verdict.startswith("EXPOSED: no raw value was sent")
    assert line == f"privacy audit: {verdict.rstrip('.')}.{_channels(audit_run(out))} Details: ppprops audit {out}"
    # resume takes the same flag; --audit off runs nothing and says how to
    with offline_llm():
        assert main(["resume", str(out), "--quiet", "--audit", "off"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == (
        f"privacy audit: not run (--audit off): 'ppprops audit {out}' checks the transcript and runs the attacks on it")
    with offline_llm():
        assert main(["resume", str(out), "--quiet", "--audit", "full", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["privacy_audit"] == line


def test_the_quick_audit_catches_a_raw_value_planted_in_a_request(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "pp"
    _run(out, capsys, "--method", "pp", "--prompt-form", "chat")
    with open_store(out) as store:
        cands = store.candidates()
    prompt = find_call(out)["body"]["messages"][0]["content"]
    c = next(c for c in cands if shown_vector(c.params_enc) in prompt)
    # as if the client had sent one shown policy's raw parameters in place of its encoded ones
    tamper_call(out, request=lambda body: body["messages"][0].update(
        content=prompt.replace(shown_vector(c.params_enc), shown_vector(c.params), 1)))
    with offline_llm():
        assert main(["resume", str(out), "--quiet"]) == 0  # a finished run prints its summary and audit again
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith(("privacy audit: LEAK: raw values were sent", "privacy audit: UNVERIFIED")), line
    assert "nothing raw was sent" not in line and f"'ppprops audit {out}' runs them" in line
    assert [f.kind for f in audit_run(out, attacks=False).leaks] == ["raw_param"]
    assert self_audit_line(out, "quick") == line
