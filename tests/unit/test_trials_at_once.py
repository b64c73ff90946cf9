"""Many trials at once (``--parallel P``): trials held by named workers, rounds of P LLM requests
from one shown history, tells in any order, failed trials kept out of every prompt and the
selection, and ``retry``. In-process, with the offline stand-in for the LLM (``EchoOptimizer``)."""

from __future__ import annotations

import json
import sqlite3
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ppprops.errors import ConfigError
from ppprops.evaluation import make_policy, run_episode
from ppprops.privacy.audit import audit_run
from ppprops.privacy.simulate import EchoOptimizer
from ppprops.settings import build_config
from ppprops.store import SCHEMA_VERSION, open_store
from ppprops.study import Study, StudyComplete, TrialsOut
from ppprops.tasks import get_task
from ppprops.values import Trial


def _config(**values: Any) -> Any:
    base = {"warmup": 4, "iterations": 8, "final_episodes": 2, "seed": 11, "select_top": 0, **values}
    return build_config(base, task=get_task("CartPole"))


def _run(study: Study, trial: Trial) -> list[float]:
    task = study.task
    env = task.make_env()
    try:
        return [run_episode(task, env, make_policy(task, trial.theta, env), s).ret for s in trial.seeds]
    finally:
        env.close()


def _prompts(run_dir: Path) -> list[tuple[int, str, int]]:
    """(iteration, prompt text, seed) of every recorded request, oldest first."""
    with open_store(run_dir) as store:
        calls = store.llm_calls()
    out = []
    for c in calls:
        body = json.loads(c["request"])
        text = body["prompt"] if "prompt" in body else body["messages"][0]["content"]
        out.append((int(c["iteration"]), text, int(body["seed"])))
    return out


def test_four_workers_hold_four_trials_and_a_fifth_waits(tmp_path: Path) -> None:
    config = _config(method="pp-hardened", parallel=4, prompt_form="chat", top_k=0)
    llm = EchoOptimizer(config.llm, spread=0.5)
    with Study.create(config, tmp_path / "s", llm=llm) as study:
        warm = [study.ask(worker=f"robot-{i}") for i in range(4)]
        assert [(t.number, t.worker, t.source) for t in warm] == [(i, f"robot-{i}", "warmup") for i in range(4)]
        assert study.ask(worker="robot-2") == warm[2]  # its own trial again: nothing new is asked
        with pytest.raises(TrialsOut, match=r"^4 trials are out, the most at once \(--parallel 4\): trial 0 \(robot-0\), "
                                            r"trial 1 \(robot-1\), trial 2 \(robot-2\), trial 3 \(robot-3\); tell one first$"):
            study.ask(worker="robot-4", wait=False)
        with pytest.raises(ConfigError, match=r"^trial 1 is held by worker 'robot-1', not 'robot-3': each worker tells"):
            study.tell(1, [1.0], worker="robot-3")
        with pytest.raises(ConfigError, match=r"^trial 1 is held by worker 'robot-1', and this tell names no worker: each worker "
                                              r"tells the trials it asked for \(ppprops tell --worker robot-1;"):
            study.tell(1, [1.0])  # a trial number without a worker is not the holder's tell
        with pytest.raises(ConfigError, match=r"^trial 6 has not been asked yet: ask hands out the next trial \(4\)$"):
            study.tell(6, [1.0])
        assert study.store.candidate_count() == 0  # none of those stored anything
        for t in reversed(warm):  # tells in any order
            study.tell(t, _run(study, t))
        assert llm.calls == 0
        first_round = [study.ask(worker=f"robot-{i}") for i in range(4)]
        assert [(t.number, t.iteration, t.source) for t in first_round] == [(4 + i, i, "llm") for i in range(4)]
        assert llm.calls == 4  # one request per LLM candidate, the round sent at once
        prompts = _prompts(tmp_path / "s")
        assert sorted(p[0] for p in prompts) == [0, 1, 2, 3]  # one recorded try per iteration, in whatever order they ended
        assert len({p[1] for p in prompts}) == 1  # one shown history for the whole round
        assert len({p[2] for p in prompts}) == 4  # each request its own keyed sampling seed
        assert prompts[0][1].count("params:") == 4  # the 4 warm-up trials, all of them
        for t in (first_round[2], first_round[0], first_round[3], first_round[1]):
            study.tell(t, _run(study, t))
        second = [study.ask(worker=f"robot-{i}") for i in range(4)]
        assert [t.number for t in second] == [8, 9, 10, 11] and llm.calls == 8
        assert _prompts(tmp_path / "s")[-1][1].count("params:") == 8
        for t in second:
            study.tell(t, _run(study, t))
        with pytest.raises(StudyComplete):
            study.ask(worker="robot-0")
        study.finalize()
    with open_store(tmp_path / "s") as store:
        cands = store.candidates()
        calls = store.llm_calls()
    assert [c.index for c in cands] == list(range(12))  # every candidate recorded once
    assert len(calls) == sum(c.source in ("llm", "fallback") for c in cands) == 8
    report = audit_run(tmp_path / "s", simulate=False, attacks=False)  # the attacks too: tests/test_parallel_trials.py (shell)
    assert report.requests == 8 and report.findings == [] and report.verdict().startswith("NOTHING RAW SENT"), report.format()


def test_a_round_waits_for_the_last_one_and_the_phase_for_the_warmup(tmp_path: Path) -> None:
    config = _config(method="pp", parallel=3, warmup=4, iterations=6, prompt_form="chat")
    with Study.create(config, tmp_path / "s", llm=EchoOptimizer(config.llm)) as study:
        a, b, c = (study.ask(worker=w) for w in ("a", "b", "c"))
        study.tell(a, _run(study, a))
        d = study.ask(worker="a")
        assert (d.number, d.phase) == (3, "warmup")
        study.tell(b, _run(study, b))
        with pytest.raises(TrialsOut, match=r"^the llm phase starts when the warmup phase is told: trial 2 \(c\), trial 3 \(a\) "
                                            "still out$"):
            study.ask(worker="b", wait=False)
        study.tell(c, _run(study, c))
        study.tell(d, _run(study, d))
        r = [study.ask(worker=w) for w in ("a", "b", "c")]
        assert [t.number for t in r] == [4, 5, 6]
        study.tell(r[0], _run(study, r[0]))
        with pytest.raises(TrialsOut, match=r"^the next round of 3 starts when the last one is told: trial 5 \(b\), trial 6 \(c\) "):
            study.ask(worker="a", wait=False)


def test_a_failed_trial_is_kept_never_shown_never_selected_and_retry_asks_it_again(tmp_path: Path) -> None:
    config = _config(method="pp", parallel=2, warmup=4, iterations=4, prompt_form="chat", top_k=0, select_top=2)
    with Study.create(config, tmp_path / "s", llm=EchoOptimizer(config.llm)) as study:
        t0, t1 = study.ask(worker="r1"), study.ask(worker="r2")
        with pytest.raises(ConfigError, match="a failed trial needs a reason"):
            study.tell(t0, failed="  ")
        study.tell(t0, failed="e-stop at 3.2 s")
        with pytest.raises(ConfigError, match=r"^trial 0 failed \(e-stop at 3.2 s\); ask it again with 'ppprops study retry"):
            study.tell(0, [1.0])
        with pytest.raises(ConfigError, match=r"^trial 1 did not fail \(it is out, held by r2\): only a failed trial can be retried$"):
            study.retry(1)
        study.tell(t1, [500.0])
        again = study.retry(0)
        assert again.number == 0 and np.array_equal(again.theta, t0.theta) and again.seeds == t0.seeds and again.worker is None
        from ppprops.summary import format_summary, run_summary

        assert "out      1 trial(s): 0 (held by nobody yet)" in format_summary(run_summary(tmp_path / "s"))  # retried, not lost
        with pytest.raises(ConfigError, match=r"^trial 0 has not been handed to a worker yet: ask for it first \(ppprops ask "):
            study.tell(0, [1.0], worker="r9")  # no worker ran it: a mistyped number must not store a return for it
        got = study.ask(worker="r3")
        assert got.number == 0 and got.worker == "r3"
        study.tell(got, failed="rig fault")  # fails again, for good
        t2, t3 = study.ask(worker="r1"), study.ask(worker="r2")
        study.tell(t2, [20.0])
        study.tell(t3, [30.0])
        while not study.done:
            ts = [study.ask(worker="r1")]
            try:
                ts.append(study.ask(worker="r2", wait=False))
            except TrialsOut:
                pass
            for t in ts:
                study.tell(t, _run(study, t) if t.source != "reeval" else [float(np.mean(_run(study, t)))] * len(t.seeds))
        with pytest.raises(StudyComplete, match=r"\(all 10 trials are settled: 9 told, 1 failed \(ppprops study retry .* TRIAL "
                                                r"asks a failed one again\)\); finalize it$"):
            study.ask(worker="r1")
        study.finalize(returns=[1.0])
        with pytest.raises(ConfigError, match=r"is finalized \(its best policy is handed over\): a failed trial can be retried only "
                                              r"before 'ppprops study finalize'$"):
            study.retry(0)  # a finalized study stays closed: its policy file is what the study found
        failed = study.failed
        assert [(t.number, why) for t, why in failed] == [(0, "rig fault")]
        reevaluated = {c.reevaluates for c in study.trials if c.reevaluates is not None}
        policy = json.loads((tmp_path / "s" / "best_policy.json").read_text())
        assert 0 not in reevaluated and policy["search"]["candidate"] != 0
    shown = _prompts(tmp_path / "s")
    assert all(p[1].count("params:") in (3, 3 + 2) for p in shown)  # trials 1-3, then the first LLM round's two; never trial 0

    s = run_summary(tmp_path / "s")
    assert s["counts"]["failed"] == 1 and s["failed_trials"] == [{"trial": 0, "source": "warmup", "worker": "r3", "reason": "rig fault"}]
    assert "failed   1 trial(s), never shown to the LLM nor selected: 0 (rig fault)" in format_summary(s)


def test_cmaes_asks_a_population_in_rounds_and_takes_tells_in_any_order(tmp_path: Path) -> None:
    config = _config(method="cmaes", parallel=4, warmup=4, iterations=20)
    with Study.create(config, tmp_path / "c") as study:
        widths = []
        while not study.done:
            ts = []
            for w in range(4):
                try:
                    ts.append(study.ask(worker=f"w{w}", wait=False))
                except (TrialsOut, StudyComplete):
                    break
            widths.append(len(ts))
            for t in reversed(ts):
                study.tell(t, _run(study, t))
        popsize = study._get_phases()[1].proposer._size  # type: ignore[attr-defined]
    assert popsize == 10  # pycma's 4 + 3 ln D for D = 10
    assert widths == [4, 4, 4, 2, 4, 4, 2]  # warm-up, then two generations of 10  # a round never reaches into the next generation before it is told


def test_worker_names_and_parallel_settings_are_checked(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"^--parallel must be in \[1, 256\], got 0$"):
        _config(method="pp", parallel=0)
    with pytest.raises(ConfigError, match=r"^--parallel 9 is larger than the budget \(--iterations 8 candidates\): use at most "):
        _config(method="pp", parallel=9)
    with pytest.raises(ConfigError, match=r"^--method r2po asks one candidate at a time .*: use --parallel 1$"):
        _config(method="r2po", parallel=4)
    config = _config(method="random", parallel=2)
    with Study.create(config, tmp_path / "s") as study:
        for bad in ("", "robot 2", "../x", "-r", "a" * 65):
            with pytest.raises(ConfigError, match="is not a plain name"):
                study.ask(worker=bad)
        assert not study.out  # nothing was asked


def test_a_store_of_schema_5_gets_workers_and_failed_trials(tmp_path: Path) -> None:
    config = _config(method="random")
    with Study.create(config, tmp_path / "s") as study:
        study.ask()
    db = sqlite3.connect(tmp_path / "s" / "run.sqlite")
    db.executescript("ALTER TABLE pending DROP COLUMN worker; DROP TABLE failed; "
                     "UPDATE meta SET value = '5' WHERE key = 'schema_version';")
    db.close()
    with open_store(tmp_path / "s") as store:
        assert store.schema_version() == SCHEMA_VERSION == 7
        (old,) = store.pending_trials()
        assert (old.number, old.worker) == (0, None) and store.failed_trials() == []
    with Study.load(tmp_path / "s") as study:
        assert study.ask(worker="robot-1").number == 0  # the trial asked before the upgrade, handed to the first worker


FAULTY = textwrap.dedent('''
    import gymnasium as gym
    import numpy as np


    class Faulty(gym.Env):
        """Raises in step for a policy whose first weight is above 3 (the robot's e-stop)."""

        def __init__(self):
            self.observation_space = gym.spaces.Box(-10.0, 10.0, (1,), dtype=np.float64)
            self.action_space = gym.spaces.Discrete(2)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.x, self.t = 0.5, 0
            return np.array([self.x]), {}

        def step(self, action):
            self.t += 1
            if int(action) == 1 and self.x > 0.45:
                raise RuntimeError("e-stop")
            self.x += 0.01 if int(action) else -0.01
            return np.array([self.x]), -abs(self.x), False, self.t >= 5, {}
''')


def test_on_episode_error_fail_trial_records_the_error_and_goes_on(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "faulty_robot.py").write_text(FAULTY)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    values = {"env": "faulty_robot:Faulty", "method": "pp", "warmup": 6, "iterations": 4, "seed": 5, "final_episodes": 1,
              "select_top": 2, "select_episodes": 1, "prompt_form": "chat", "top_k": 0, "on_episode_error": "fail-trial",
              "parallel": 2}
    config = build_config(values)
    seen: dict[str, list[Any]] = {"start": [], "candidate": [], "failed": []}
    from ppprops.events import RunEvents

    events = RunEvents(on_start=lambda done, total: seen["start"].append((done, total)),
                       on_candidate=lambda c, lat, best: seen["candidate"].append(c.index),
                       on_failed=lambda n, why: seen["failed"].append(n))
    with Study.create(config, tmp_path / "r", llm=EchoOptimizer(config.llm)) as study:
        study.optimize(events=events)
        failed = study.failed
        cands = study.trials
    assert failed and all("raised in step" in why and "RuntimeError: e-stop" in why for _, why in failed)
    # a progress display counts every place in the plan: the candidates and the failed trials make up its total
    assert seen["start"] == [(0, 12)] and sorted(seen["candidate"] + seen["failed"]) == list(range(12))
    assert seen["failed"] == [t.number for t, _ in failed]
    assert sorted([c.index for c in cands] + [t.number for t, _ in failed]) == list(range(12))
    fail_enc = {t.number for t, _ in failed}
    assert not fail_enc & {c.reevaluates for c in cands if c.reevaluates is not None}  # never re-evaluated by the selection
    from ppprops.summary import format_summary, run_summary

    s = run_summary(tmp_path / "r")
    assert [f["trial"] for f in s["failed_trials"]] == sorted(fail_enc) and s["counts"]["failed"] == len(fail_enc)
    assert f"failed   {len(fail_enc)} trial(s), never shown to the LLM nor selected: " in format_summary(s)
    for it, text, _ in _prompts(tmp_path / "r"):
        told_before = [c for c in cands if c.index < 6 + (it // 2) * 2 and c.reevaluates is None]
        assert text.count("return:") == len(told_before)  # exactly the told candidates: no failed trial
    policy = json.loads((tmp_path / "r" / "best_policy.json").read_text())
    assert policy["search"]["candidate"] not in fail_enc


ALWAYS = FAULTY.replace("if int(action) == 1 and self.x > 0.45:", "if True:")


@pytest.mark.parametrize("select_top", [2, 0])
def test_a_search_whose_every_trial_failed_ends_with_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, select_top: int) -> None:
    """Every trial fails (the env raises in every episode): the study says so in one line, at the
    selection stage or at the final evaluation, and keeps every failed trial with its reason."""
    (tmp_path / "dead_robot.py").write_text(ALWAYS)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    values = {"env": "dead_robot:Faulty", "method": "random", "warmup": 3, "iterations": 2, "seed": 5, "final_episodes": 1,
              "select_top": select_top, "select_episodes": 1, "on_episode_error": "fail-trial"}
    with Study.create(build_config(values), tmp_path / "r") as study:
        with pytest.raises(ConfigError, match=r"^every search trial failed \(5 of 5; the first, trial 0: .*RuntimeError: e-stop .*\): "
                                              r"there is no candidate to re-evaluate or hand over; 'ppprops show .*' lists each "
                                              r"reason, and once the evaluation is fixed 'ppprops study retry .* TRIAL' asks a "
                                              r"failed trial again$"):
            study.optimize()
            study.finalize()
        assert [t.number for t, _ in study.failed] == [0, 1, 2, 3, 4] and study.trials == []
    assert not (tmp_path / "r" / "best_policy.json").exists()


def test_a_run_whose_every_trial_failed_exits_2_with_one_line_and_so_does_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from ppprops.cli import main

    (tmp_path / "dead_robot.py").write_text(ALWAYS)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    args = ["run", "--env", "dead_robot:Faulty", "--method", "random", "--warmup", "3", "--iterations", "2", "--final-episodes", "1",
            "--on-episode-error", "fail-trial", "--out", "r", "--quiet"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert [line.split(":")[0] for line in err] == ["note"] * 5 + ["ppprops"], err  # a note per failed trial, then the error
    assert err[-1].startswith("ppprops: error: every search trial failed (5 of 5; the first, trial 0: "), err
    assert main(["resume", "r", "--quiet"]) == 2
    again = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("note: ")]
    assert len(again) == 1 and again[0].startswith("ppprops: error: every search trial failed (5 of 5; "), again
    assert main(["show", "r", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["counts"]["failed"] == 5 and [f["trial"] for f in s["failed_trials"]] == [0, 1, 2, 3, 4]


def test_show_lists_a_trial_asked_without_a_worker_name(tmp_path: Path) -> None:
    from ppprops.summary import format_summary, run_summary

    with Study.create(_config(method="random"), tmp_path / "one") as study:
        study.ask()
    assert "out      1 trial(s): 0 (held by the unnamed worker)" in format_summary(run_summary(tmp_path / "one"))
    with Study.create(_config(method="random", parallel=4), tmp_path / "four") as study:
        study.ask()  # the warm-up's first four trials are made at once: the first is the unnamed worker's, the rest nobody's
    assert ("out      4 trial(s): 0 (held by the unnamed worker), 1 (held by nobody yet), 2 (held by nobody yet), "
            "3 (held by nobody yet)") in format_summary(run_summary(tmp_path / "four"))


def test_the_embedded_server_gets_p_slots(tmp_path: Path) -> None:
    """At --parallel P the embedded model's server is started with P slots (each with the whole
    context size), so a round's requests are decoded together; at P = 1 its command is as before."""
    from ppprops.llm.embedded import _command

    config = _config(method="pp", parallel=4)
    with Study.create(config, tmp_path / "s") as study:
        client = study._phases.llm().inner  # connected lazily: nothing is started before the first request
        server = client._server  # type: ignore[attr-defined]
        assert (server.func.__name__, server.keywords) == ("EmbeddedServer", {"context_size": 16384, "slots": 4})
    with Study.create(_config(method="pp"), tmp_path / "one") as study:
        assert study._phases.llm().inner._server.__name__ == "_own_server"  # type: ignore[attr-defined]
    model = Path("m.gguf")
    assert _command(model, 16384, 1)[-2:] == ["--threads", "1"]
    assert _command(model, 16384, 1, 4)[-4:] == ["--threads", "1", "--slots", "4"]
