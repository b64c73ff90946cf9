"""The document form: the history as a document for the embedded base model to continue.

Guards the mechanics, not the search quality (that is benchmark 6 in benchmarks/RESULTS.md): the
format sent, the grammar, the parsing of what comes back, which vector is evaluated, and the audit.
One short real search with the embedded model is shared by the module.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppprops import rundir
from ppprops.client import hardening
from ppprops.client.context import prompt_context
from ppprops.client.hardening import codec_for
from ppprops.config import LLMConfig, RunConfig
from ppprops.errors import ConfigError
from ppprops.llm.embedded import default_threads
from ppprops.methods import resolve
from ppprops.privacy.audit import audit_run
from ppprops.proposers import LLMProposer
from ppprops.proposers.base import clip_to_box
from ppprops.proposers.llm import LLMSearch, stall_count
from ppprops.runner import load_run, start
from ppprops.seeding import Streams
from ppprops.store import open_store
from ppprops.wire import EncodedEntry, PromptContext, build_document, continuation_grammar, document_target, read_continuation
from ppprops.wire.document import document_temperature
from ppprops.wire.forms import DOCUMENT
from ppprops.wire.transcript import open_target

from support import tamper_call


def _ctx(**kw: object) -> PromptContext:
    base = dict(summary="s", observations=(("x", "x"), ("v", "v")), actions=("left", "right"), discrete=True,
                reward_text="r", hints="", encoded_params=True, scaled_rewards=True, detailed_feedback=True,
                param_range=None, optimum=None, title="CartPole")
    base.update(kw)
    return PromptContext(**base)  # type: ignore[arg-type]


HISTORY = [
    EncodedEntry(3, (0.5, 14.26, -300.4, 1.0, 2.0, 0.001), 5.0, (("c", 1.0),), (("episode_length", 12.0),)),
    EncodedEntry(7, (3.1, -0.2, 5.5, 0.0, -7.25, 8.0), 7.5),
]


# -- the prompt: format, target, grammar ---------------------------------------------------------------
def test_document_is_header_labelled_entries_lowest_first_and_an_open_block() -> None:
    doc = build_document(_ctx(), HISTORY)
    header, *blocks = doc.split("\n\n")
    assert header.startswith("# CartPole: linear policy search.")
    assert blocks == [
        "return: 5.00\nparams: [0:0.50,1:14.3,2:-300,3:1.00,4:2.00,5:0.00]",
        "return: 7.50\nparams: [0:3.10,1:-0.20,2:5.50,3:0.00,4:-7.25,5:8.00]",
        "return: 8.00\nparams: [",  # best 7.5 + 0.2 * (7.5 - 5.0)
    ]
    # returns and parameters only: no reward components, diagnostics or instructions
    assert "components" not in doc and "episode_length" not in doc and "JSON" not in doc


def test_document_uses_the_list_form_whatever_the_parameter_style() -> None:
    assert build_document(_ctx(params_style="indexed"), HISTORY) == build_document(_ctx(), HISTORY)


def test_target_is_computed_from_the_shown_encoded_returns_only() -> None:
    assert document_target(HISTORY) == pytest.approx(8.0)
    one = [EncodedEntry(0, (1.0,), -40.0)]
    assert document_target(one) == pytest.approx(-40.0 + 0.2 * 4.0)  # spread floor: 10% of |best|
    assert document_target([EncodedEntry(0, (1.0,), 0.0)]) == 0.0
    # negative returns: never asked to turn positive (at most |best| * 0.2 above the best)
    neg = [EncodedEntry(0, (1.0,), -500.0), EncodedEntry(1, (2.0,), -78.0)]
    assert document_target(neg) == pytest.approx(-78.0 + 0.2 * 78.0)
    with pytest.raises(ValueError):
        document_target([])


def test_temperature_alternates_and_rises_on_retries() -> None:
    assert [document_temperature(i, 0) for i in range(4)] == [0.6, 1.0, 0.6, 1.0]
    assert document_temperature(0, 2) == pytest.approx(1.2) and document_temperature(1, 5) == 2.0
    assert document_temperature(3, 0, 0.3) == 0.3 and document_temperature(3, 1, 0.3) == pytest.approx(0.6)


def test_grammar_fits_each_coordinate_to_the_widest_value_printed_there() -> None:
    g = continuation_grammar(6, HISTORY, _ctx())
    root, *rules = g.strip().split("\n")
    # widest printed values per coordinate: 3.10 (1 integer digit), 14.3 (2), -300 (3), 1.00, -7.25, 8.00 (1)
    assert root == 'root ::= "0:" w1 ",1:" w2 ",2:" w3 ",3:" w1 ",4:" w1 ",5:" w1 "]"'
    # numbers as the list form prints them at 3 significant digits, 2 decimals at most
    assert rules == ['w1 ::= "-"? ("0" ("." [0-9] [0-9]?)? | [1-9] ("." [0-9] [0-9]?)?)',
                     'w2 ::= "-"? ("0" ("." [0-9] [0-9]?)? | [1-9] ("." [0-9] [0-9]?)? | [1-9] [0-9] ("." [0-9])?)',
                     'w3 ::= "-"? ("0" ("." [0-9] [0-9]?)? | [1-9] ("." [0-9] [0-9]?)? | [1-9] [0-9] ("." [0-9])? '
                     '| [1-9] [0-9] [0-9])']
    two = continuation_grammar(6, HISTORY, _ctx(param_digits=2)).split("\n")[1]
    assert two == 'w1 ::= "-"? ("0" ("." [0-9] [0-9]?)? | [1-9] ("." [0-9])?)'
    assert continuation_grammar(3).startswith('root ::= "0:" num ",1:" num ",2:" num "]"')
    with pytest.raises(ValueError):
        continuation_grammar(5, HISTORY, _ctx())


# -- what comes back -----------------------------------------------------------------------------------
@pytest.mark.parametrize("text,values,error", [
    ("0:1.5,1:-2,2:30]", (1.5, -2.0, 30.0), None),
    ("1.5,-2,30]", (1.5, -2.0, 30.0), None),  # no labels (an endpoint without the grammar)
    ("0:1.5,2:-2,1:30]", None, "labels"),
    ("1.5,-2,30]\n\nreturn: 9.00\nparams: [4,5,6]", (1.5, -2.0, 30.0), None),  # more document: ignored
    ("1.5,\u22122,30]", (1.5, -2.0, 30.0), None),  # a typographic minus sign
    ("1.5,-2]", None, "wrong_length"),
    ("1.5,-2,30", None, "truncated"),
    ("", None, "empty"),
    ("nan,1,2]", None, "non_finite"),
])
def test_continuation_is_read_up_to_the_first_closing_bracket(text: str, values: tuple[float, ...] | None,
                                                              error: str | None) -> None:
    r = read_continuation(text, 3)
    assert r.values == values and r.error == error


def test_labels_out_of_order_make_an_entry_unreadable_for_the_audit() -> None:
    doc = build_document(_ctx(), HISTORY)
    assert [e.params for e in DOCUMENT.entries(doc)] == [
        ("0.50", "14.3", "-300", "1.00", "2.00", "0.00"), ("3.10", "-0.20", "5.50", "0.00", "-7.25", "8.00")]
    swapped = doc.replace("[0:3.10,1:-0.20", "[1:3.10,0:-0.20")
    assert DOCUMENT.entries(swapped)[1].params == ("(indices out of order)",)


def test_continuation_cut_at_the_token_limit_is_never_used() -> None:
    assert read_continuation("1,2,3]", 3, finish_reason="length").error == "length"


# -- configuration ---------------------------------------------------------------------------------------
def _config(**kw: object) -> RunConfig:
    base = dict(task="CartPole", method="pp", mechanisms=resolve("pp"), warmup=4, iterations=4, final_episodes=2, seed=3, select_top=0)
    base.update(kw)
    return RunConfig(**base)  # type: ignore[arg-type]


def test_auto_is_the_document_form_for_the_embedded_model_only() -> None:
    assert _config().form == "document"
    assert _config(llm=LLMConfig(base_url="http://localhost:1/v1", model="m")).form == "chat"
    assert _config(prompt_form="chat").form == "chat"
    assert _config(method="r2po", mechanisms=resolve("vanilla")).form == "chat"
    with pytest.raises(ConfigError, match="r2po"):
        _config(method="r2po", mechanisms=resolve("vanilla"), prompt_form="document").validate()
    with pytest.raises(ConfigError, match="prompt-form"):
        _config(prompt_form="doc").validate()
    assert (_config().digits(), _config(prompt_form="chat").digits(), _config(param_digits=4).digits()) == (2, 3, 4)
    stored = _config().to_json()
    del stored["prompt_form"]  # a run stored before the document form existed resumes as it ran: chat
    assert RunConfig.from_json(stored).form == "chat"


@pytest.mark.parametrize("cores,load,threads", [(2, 0.1, 2), (2, 0.6, 1), (2, 1.2, 1), (2, 11.0, 1), (16, 3.2, 13)])
def test_threads_leave_busy_cores_alone(cores: int, load: float, threads: int) -> None:
    assert default_threads(cores, load) == threads


# -- one real search with the embedded model ---------------------------------------------------------------
@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("doc") / "run"
    # fixed secrets and run id (which keys the streams) for the audit's findings: on fresh ones an attack
    # reads a value by chance now and then
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(hardening, "os_rng", lambda: np.random.default_rng(3))
        mp.setattr(rundir, "new_run_id", lambda config: f"{config.task}__{config.method}__{config.seed}__20261204-000000-0000")
        start(_config(), out)
    return out


@pytest.mark.llm
def test_requests_are_completions_of_the_document_with_its_grammar(run_dir: Path) -> None:
    store, cfg, secrets = load_run(run_dir)
    try:
        cands, calls = store.candidates(), store.llm_calls()
    finally:
        store.close()
    task = cfg.make_task()
    codec = codec_for(secrets, task, cfg.encoding)
    rebuilt = LLMProposer(LLMSearch(llm=None, codec=codec, context=prompt_context(task, cfg.prompt, codec), top_k=cfg.top_k,  # type: ignore[arg-type]
                                    box=cfg.box, streams=Streams(cfg.seed)), form=DOCUMENT)
    by_iteration: dict[int, list[dict[str, object]]] = {}
    for c in calls:
        by_iteration.setdefault(int(c["iteration"]), []).append(c)
    assert sorted(by_iteration) == [0, 1, 2, 3]
    for c in cands:
        if c.source == "warmup":
            rebuilt.tell(c)
            continue
        for call in by_iteration[c.iteration]:
            body = json.loads(str(call["request"]))
            assert "messages" not in body and body["prompt"] == rebuilt.prompt()  # exactly the document, nothing else
            assert body["prompt"].endswith("\nparams: [")
            assert body["grammar"] == continuation_grammar(task.D, rebuilt.shown(), rebuilt.ctx)
            stalled = stall_count(cands[: c.index])  # LLM iterations in a row without a new best before this one
            assert body["temperature"] == document_temperature(c.iteration, int(call["attempt"]), None, stalled)
            assert json.loads(str(call["response"]))["object"] == "text_completion"  # the completions endpoint
        last = by_iteration[c.iteration][-1]
        if c.source == "llm":  # the evaluated vector is the continuation the model wrote, decoded and clipped
            values = read_continuation(str(last["content"]), task.D).values
            assert values is not None
            theta, _ = clip_to_box(codec.decode(np.asarray(values)), cfg.box)
            assert c.params == pytest.approx(theta)
        rebuilt.tell(c)


@pytest.mark.llm
def test_audit_reads_every_document_entry_and_its_target(run_dir: Path) -> None:
    # the transcript's checks only: what the simulator attacks get from a handful of entries follows
    # the model's answers, which vary with the cores' load (tests/test_simulator_attacks.py covers them)
    report = audit_run(run_dir, simulate=False)
    # nothing raw sent and every byte accounted for; a pp run is EXPOSED by the channels the paper's
    # scheme keeps (the lattice, the small run seed's warm-up), which the form does not change
    assert not report.leaks and not report.unverified, report.format()
    assert all(f.by_design or f.kind == "seed-replay" for f in report.exposed), report.format()  # run seed 3 is small
    store = open_store(run_dir)
    try:
        prompts = [json.loads(c["request"])["prompt"] for c in store.llm_calls()]
    finally:
        store.close()
    assert report.requests == len(prompts)
    assert report.entries == sum(len(DOCUMENT.entries(p)) for p in prompts) >= 4 * len(prompts)
    assert not [f for f in report.findings if f.kind == "target"]


@pytest.mark.llm
@pytest.mark.parametrize("tamper,kind", [("raw_return", "raw_return"), ("target", "target")])
def test_audit_flags_a_raw_return_or_a_wrong_target_in_a_document(run_dir: Path, tmp_path: Path, tamper: str,
                                                                   kind: str) -> None:
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    with open_store(copy) as store:
        # a raw return the audit must call raw_return: not the optimum (500), which it names as such
        optimum = RunConfig.from_json(store.config()).make_task().optimal_return
        best_raw = max(c.ret for c in store.candidates() if c.ret != optimum)

    def retarget(body: dict[str, Any]) -> None:  # the last recorded request
        at, tok = open_target(body["prompt"])  # type: ignore[misc]
        new = f"{best_raw:.2f}" if tamper == "raw_return" else f"{float(tok) + 1.0:.2f}"
        body["prompt"] = body["prompt"][:at] + new + body["prompt"][at + len(tok):]

    tamper_call(copy, request=retarget)
    report = audit_run(copy)
    assert not report.clean
    assert kind in {f.kind for f in report.leaks + report.unverified}


# -- the audit of document-form requests, offline (no model): fields replayed, tampering found ---------------
def _offline_document_run(root: Path, name: str = "off", **kw: object) -> Path:
    from support import offline_llm

    out = root / name
    with offline_llm():
        start(replace(_config(), iterations=4, final_episodes=0, seed=123456789, **kw), out)
    return out


def test_offline_document_run_is_accounted_for_byte_by_byte(tmp_path: Path) -> None:
    run_dir = _offline_document_run(tmp_path)
    store = open_store(run_dir)
    try:
        calls = store.llm_calls()
        cands = store.candidates()
        bodies = [json.loads(c["request"]) for c in calls]
    finally:
        store.close()
    assert bodies and all("prompt" in b and "messages" not in b and "grammar" in b for b in bodies)
    warmup = sum(c.source == "warmup" for c in cands)
    assert [b["temperature"] for b in bodies] == [document_temperature(c["iteration"], c["attempt"], None, stall_count(cands[: warmup + c["iteration"]]))
                                                  for c in calls]
    report = audit_run(run_dir)
    assert not report.leaks and not report.unverified, report.format()
    assert report.requests == len(bodies)


@pytest.mark.parametrize("field,value,why", [
    ("temperature", 1.9876543, "field temperature differs"),  # not the form's for iteration 3 (nor, at 7 decimals, a raw value)
    ("grammar", 'root ::= "0:1"', "field grammar differs"),  # not the grammar of the history shown
    ("response_format", {"type": "json_object"}, "field response_format, which the client does not send"),
    ("user", "x", "field user, which the client never sends"),
])
def test_a_document_request_the_client_would_not_send_is_unverified(tmp_path: Path, field: str, value: object, why: str) -> None:
    run_dir = _offline_document_run(tmp_path)
    tamper_call(run_dir, request=lambda body: body.update({field: value}))
    report = audit_run(run_dir)
    assert any(why in f.detail for f in report.unverified), report.format()


def test_a_raw_return_planted_in_a_document_field_is_a_leak(tmp_path: Path) -> None:
    run_dir = _offline_document_run(tmp_path)
    store = open_store(run_dir)
    try:
        raw = min(c.ret for c in store.candidates() if c.ret != 500.0)  # not the optimum (that finding has its own kind)
    finally:
        store.close()
    tamper_call(run_dir, request=lambda body: body.update(user=f"best {raw:.4f}"))
    assert "raw_return" in {f.kind for f in audit_run(run_dir).leaks}
