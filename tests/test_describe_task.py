"""`--describe-task on|off`: ProPS+ (the prompt describes the task) against ProPS (it does not)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ppprops.cli import main, run_config, run_parser
from ppprops.client.codec import Codec
from ppprops.client.context import prompt_context
from ppprops.client.secrets import Secrets
from ppprops.methods import METHODS, MethodKind, resolve
from ppprops.privacy.audit import audit_run
from ppprops.tasks import get_task
from ppprops.wire import EncodedEntry, build_prompt
from ppprops.wire.prompt import task_section
from ppprops.wire.r2po import Evidence, build_critic_prompt

from support import make_config, offline_llm


def _contexts(task_name: str, method: str):  # type: ignore[no-untyped-def]
    task = get_task(task_name)
    secrets = Secrets(run_id="r", a=np.full(task.D, 2.0), c=3.0)
    on = make_config(task_name, method)
    off = replace(on, mechanisms=resolve(method, describe_task=False))
    codec = Codec(secrets, encode_params=on.mechanisms.encode_params, scale_rewards=on.mechanisms.scale_rewards)
    return task, prompt_context(task, on.prompt, codec), prompt_context(task, off.prompt, codec)


def _described(task) -> list[str]:  # type: ignore[no-untyped-def]
    """Every piece of task description the prompt may carry."""
    t = task.text
    return [t.summary.strip(), *t.observations, *t.actions, t.reward_structure.strip(), t.reward_hint.strip(), t.hints.strip()]


@pytest.mark.parametrize("task_name,method", [("CartPole", "vanilla"), ("CartPole", "pp"), ("Ant-Ultra", "df"), ("Highway", "pe")])
def test_off_leaves_only_the_policy_structure(task_name: str, method: str) -> None:
    task, on, off = _contexts(task_name, method)
    history = [EncodedEntry(0, tuple(0.5 for _ in range(task.D)), 12.0)]
    with_task, without = build_prompt(on, history), build_prompt(off, history)
    for piece in _described(task):
        if piece:
            assert piece not in without, piece
    assert task.text.summary.strip() in with_task and all(o in with_task for o in task.text.observations)
    rule = "The output with the highest value selects the action." if task.discrete else "clipped to the actuator limits"
    structure = task_section(off)
    assert f"The state s has {task.n_s} values and the policy has {task.n_a} outputs." in structure and rule in structure
    # everything but the task section is the same prompt: parameters, feedback, interaction, history
    assert without == with_task.replace(task_section(on), structure)
    assert f"params has {task.D} entries" in without and "Here is the history" in without


def test_on_by_default_for_every_method_and_stored(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    for m in METHODS.values():
        if m.kind is MethodKind.PROMPTED:
            assert m.preset is not None and m.preset.describe_task
            assert run_config(run_parser().parse_args(["--env", "CartPole", "--method", m.name])).mechanisms.describe_task
    cfg = run_config(run_parser().parse_args(["--env", "CartPole", "--method", "vanilla", "--describe-task", "off"]))
    assert cfg.mechanisms == replace(resolve("vanilla"), describe_task=False)
    toml = tmp_path / "run.toml"
    toml.write_text('env = "CartPole"\nmethod = "pp"\ndescribe-task = false\nwarmup = 2\niterations = 2\nfinal-episodes = 0\n')
    with offline_llm():
        assert main(["run", "--config", str(toml), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["show", str(tmp_path / "r"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["mechanisms"]["describe_task"] is False and s["config"]["mechanisms"]["describe_task"] is False


def test_the_sent_prompts_carry_no_description_and_are_audited(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    task = get_task("Acrobot")
    with offline_llm():
        # the chat form: the document form (the embedded model's default) carries no task text at all
        assert main(["run", "--env", "Acrobot", "--method", "pp", "--describe-task", "off", "--warmup", "3", "--iterations", "3",
                     "--prompt-form", "chat", "--final-episodes", "0", "--out", str(tmp_path / "r"), "--quiet",
                     "--audit", "full"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "privacy audit: EXPOSED: no raw value was sent" in out  # pp: the paper's channels, nothing else
    report = audit_run(tmp_path / "r")
    assert report.requests == 3 and not report.leaks and not report.unverified
    import sqlite3

    with sqlite3.connect(tmp_path / "r" / "run.sqlite") as con:
        prompts = [json.loads(r[0])["messages"][0]["content"] for r in con.execute("SELECT request FROM llm_calls")]
    assert len(prompts) == 3
    for p in prompts:
        assert task.text.summary.strip() not in p and task.text.hints.strip() not in p
        assert "Not given: find the policy from the numbers alone." in p


def test_the_r2po_critic_follows_the_switch() -> None:
    task, on, off = _contexts("CartPole", "r2po")
    ev = Evidence(params=(0.1,) * task.D, returns=(10.0, 1.0, 9.0, 11.0), episodes=3, diagnostics=(), median_return=10.0,
                  median_rollout=(((0.0, 0.1, 0.2, 0.3), "1"),))  # fmt: skip
    assert task.text.summary.strip() in build_critic_prompt(on, ev)
    assert task.text.summary.strip() not in build_critic_prompt(off, ev) and task_section(off) in build_critic_prompt(off, ev)
