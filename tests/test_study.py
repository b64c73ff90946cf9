"""The study (ppprops.study): ask/tell by hand gives what the runner's loop gives, crash safety
between ask and tell, one LLM call per slot across processes, and tell's checks.

A fixed chat (``privacy.simulate.EchoOptimizer``, deterministic for a request seed) stands in for
the LLM, so every trial can be compared value for value.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from golden_cases import CASES, case_config, case_secrets, golden_record, run_case

from ppprops.errors import ConfigError
from ppprops.evaluation import make_policy, run_episode
from ppprops.privacy.simulate import EchoOptimizer
from ppprops.proposers.base import StopSearch
from ppprops.status import RunStatus
from ppprops.store import open_store
from ppprops.study import Study, StudyComplete

GOLDEN = json.loads((Path(__file__).parent / "data" / "golden_study.json").read_text())
SRC = str(Path(__file__).resolve().parents[1] / "src")


@pytest.mark.parametrize("name", sorted(CASES))
def test_the_study_loop_gives_the_pinned_runs(tmp_path: Path, name: str) -> None:
    """Same seeds, secrets and chat give the same candidates, request bodies and final evaluation
    as the search core before it became a loop over the study (tests/data/golden_study.json)."""
    run_case(name, tmp_path / name)
    assert golden_record(tmp_path / name) == GOLDEN[name]


def _episodes(study: Study, theta: np.ndarray, seeds: tuple[int, ...]) -> tuple[list[float], list[dict[str, float]], list[dict[str, Any]]]:
    """Run the trial's episodes ourselves, as a user with their own simulator would."""
    task = study.task
    env = task.make_env()
    try:
        eps = [run_episode(task, env, make_policy(task, theta, env), s) for s in seeds]
    finally:
        env.close()
    return [e.ret for e in eps], [e.components for e in eps], [e.diagnostics for e in eps]


@pytest.mark.parametrize("name", ["pp-document", "vanilla-2ep", "cmaes"])
def test_ask_tell_by_hand_gives_the_same_run_as_the_loop(tmp_path: Path, name: str) -> None:
    config = case_config(name)
    with Study.create(config, tmp_path / "hand", secrets=case_secrets(name, config), llm=EchoOptimizer(config.llm, spread=0.5)) as study:
        while not study.done:
            trial = study.ask()
            assert study.ask() == trial  # asked again before the tell: the same trial, no second proposal
            returns, components, diagnostics = _episodes(study, trial.theta, trial.seeds)
            study.tell(trial, returns, components=components, diagnostics=diagnostics)
        study.finalize()
    run_case(name, tmp_path / "loop")
    assert golden_record(tmp_path / "hand") == golden_record(tmp_path / "loop") == GOLDEN[name]
    assert json.loads((tmp_path / "hand" / "best_policy.json").read_text())["theta"] == \
        json.loads((tmp_path / "loop" / "best_policy.json").read_text())["theta"]


@pytest.fixture
def study(tmp_path: Path) -> Study:
    config = case_config("pp-chat")
    s = Study.create(config, tmp_path / "s", secrets=case_secrets("pp-chat", config), llm=EchoOptimizer(config.llm))
    yield s
    s.close()


def test_tell_refuses_bad_feedback_and_stores_nothing(study: Study) -> None:
    trial = study.ask()
    bad: list[tuple[dict[str, Any], str]] = [
        ({"returns": float("nan")}, "not a finite number"),
        ({"returns": [1.0, float("inf")]}, "not a finite number"),
        ({"returns": []}, "at least one episode"),
        ({"returns": 1.0, "diagnostics": {"speed": 3.0}}, "unknown diagnostic 'speed'"),
        ({"returns": 1.0, "components": {"reward_x": 1.0}}, "unknown component 'reward_x'"),
        ({"returns": [1.0, 2.0], "diagnostics": {"episode_length": 3.0}}, "one mapping per episode"),
        ({"returns": 1.0, "diagnostics": {"termination": float("nan")}}, r"^diagnostic 'termination' = nan is neither a finite number nor a text$"),
        ({"returns": 1.0, "diagnostics": {"termination": [1]}}, "neither a finite number nor a text"),
        # episode_length is the episode's steps (the audit's clock reads it): a word, NaN or a negative count is refused
        ({"returns": 1.0, "diagnostics": {"episode_length": "abc"}}, r"^diagnostic 'episode_length' = 'abc' is not a number of steps$"),
        ({"returns": 1.0, "diagnostics": {"episode_length": float("nan")}}, "'episode_length' = nan is not a number of steps"),
        ({"returns": 1.0, "diagnostics": {"episode_length": -3}}, "'episode_length' = -3 is not a number of steps"),
    ]
    for kwargs, message in bad:
        with pytest.raises(ConfigError, match=message):
            study.tell(trial, kwargs.pop("returns"), **kwargs)
    assert study.store.candidate_count() == 0 and study.pending == trial  # nothing stored, still pending
    with pytest.raises(ConfigError, match=r"^trial 5 has not been asked yet: ask hands out the next trial \(1\)$"):
        study.tell(5, 1.0)
    moved = type(trial)(**{**trial.__dict__, "theta": trial.theta + 1.0})
    with pytest.raises(ConfigError, match="does not hold the parameters the study asked for"):
        study.tell(moved, 1.0)
    cand = study.tell(trial, [10.0, 20.0], diagnostics=[{"episode_length": 10.0}, {"episode_length": 20.0}])
    assert cand.ret == 15.0 and cand.feedback.diagnostics == {"episode_length": 15.0}
    assert cand.feedback_enc.ret == pytest.approx(study.secrets.c * 15.0)  # r~ = c r (Eq. 7)
    assert np.allclose(cand.params_enc, study.secrets.a * trial.theta)  # theta~ = A theta (Eq. 5)
    with pytest.raises(ConfigError, match="trial 0 was already told"):
        study.tell(trial, 1.0)
    assert study.store.candidate_count() == 1


def test_a_component_the_task_declares_must_be_told(tmp_path: Path) -> None:
    from ppprops.settings import build_config
    from ppprops.tasks import get_task

    config = build_config({"method": "random", "warmup": 2, "iterations": 1, "seed": 1}, task=get_task("Ant-Ultra"))
    with Study.create(config, tmp_path / "ant") as study:
        trial = study.ask()
        with pytest.raises(ConfigError, match="component 'reward_contact' is missing"):
            study.tell(trial, 1.0, components={"reward_forward": 1.0, "reward_survive": 1.0, "reward_ctrl": -0.5})
        assert study.store.candidate_count() == 0


def test_ask_after_the_budget_and_finalize_with_the_users_own_episodes(study: Study) -> None:
    while not study.done:
        trial = study.ask()
        n = len(trial.seeds)  # one return per episode asked for (a re-evaluation asks for 10)
        study.tell(trial, [float(trial.number)] * n, diagnostics=[{"episode_length": float(trial.number)}] * n)
    with pytest.raises(StudyComplete, match="nothing more to ask .all 15 trials are told."):
        study.ask()
    fe = study.finalize(returns=[7.0, 9.0])
    assert fe is not None and fe.returns == (7.0, 9.0) and fe.candidate_index == study.best.index  # type: ignore[union-attr]
    assert study.status == (RunStatus.FINISHED, "")
    doc = json.loads((study.run_dir / "best_policy.json").read_text())
    assert doc["theta"] == [float(v) for v in study.trials[fe.candidate_index].params]
    assert np.array_equal(study.policy().theta, study.trials[fe.candidate_index].params)


def test_the_lucky_one_episode_candidate_is_not_handed_over(study: Study) -> None:
    """Candidate 9 had the best single episode (500), candidate 8 is the better policy.
    The selection stage re-runs the top 5 on 10 fresh episodes each; the pooled mean picks 8."""
    search = {9: 500.0, 8: 400.0, 7: 300.0, 6: 200.0, 5: 100.0}
    reeval = {9: [60.0] * 10, 8: [420.0] * 10, 7: [310.0] * 10, 6: [150.0] * 10, 5: [90.0] * 10}
    while not study.done:
        trial = study.ask()
        if trial.reevaluates is None:
            ret = search.get(trial.number, 10.0)
            study.tell(trial, ret, diagnostics={"episode_length": ret})
        else:
            assert trial.source == "reeval" and trial.phase == "selection" and len(trial.seeds) == 10
            assert np.array_equal(trial.theta, study.trials[trial.reevaluates].params)  # the same policy, fresh episodes
            r = reeval[trial.reevaluates]
            study.tell(trial, r, diagnostics=[{"episode_length": x} for x in r])
    cands = study.trials
    assert [c.reevaluates for c in cands[10:]] == [9, 8, 7, 6, 5]  # the top 5 by search return, best first
    assert len({s for c in cands[10:] for s in c.seeds} & {s for c in cands[:10] for s in c.seeds}) == 0  # fresh seeds
    assert study.best is not None and study.best.index == 8  # pooled: 8 -> (400 + 4200) / 11, 9 -> (500 + 600) / 11
    fe = study.finalize(returns=[1.0])
    assert fe is not None and fe.candidate_index == 8
    doc = json.loads((study.run_dir / "best_policy.json").read_text())
    assert doc["search"]["candidate"] == 8 and doc["search"]["selection"] == {"mean": pytest.approx(4600 / 11), "episodes": 11}
    from ppprops.loop import best_candidate, search_candidates

    assert best_candidate(search_candidates(cands)).index == 9  # the old rule would have handed over the lucky one
    from ppprops.summary import format_summary, run_summary

    summary = run_summary(study.run_dir)  # the extra episodes are stored and counted
    assert summary["counts"]["episodes"] == {"search": 10, "selection": 50, "final": 1}
    assert summary["counts"]["by_source"]["reeval"] == 5 and summary["best"]["index"] == 8
    assert summary["best"]["search_best"] == {"return": 500.0, "index": 9}
    text = format_summary(summary)
    assert "episodes 10 in the search, 50 re-evaluating the best candidates, 1 in the final evaluation" in text
    assert "best     candidate 8: mean 418.18 over 11 episodes" in text and "single search return was 500.00 (candidate 9)" in text


def test_a_callback_returning_false_stops_the_search_cleanly(tmp_path: Path) -> None:
    from ppprops.runner import start

    config = case_config("random")
    seen: list[int] = []

    def stop_at_six(cand: Any, study: Study) -> bool:
        seen.append(cand.index)
        return cand.index < 6

    start(config, tmp_path / "r", callbacks=[stop_at_six])
    with open_store(tmp_path / "r") as store:
        assert store.status() == "stopped: stopped by a callback"
        assert store.candidate_count() == 7 and seen == list(range(7))
        assert store.final_eval() is not None  # the best so far was still evaluated
    assert (tmp_path / "r" / "best_policy.json").exists()


def test_cmaes_population_size_is_an_option_of_the_method(tmp_path: Path) -> None:
    from ppprops.settings import build_config
    from ppprops.tasks import get_task

    config = build_config({"method": "cmaes", "warmup": 3, "iterations": 8, "seed": 2, "method_options": {"popsize": 4}},
                          task=get_task("CartPole"))
    with Study.create(config, tmp_path / "c") as study:
        study.optimize()
        assert study.store.candidate_count() == 16  # 3 warm-up + 8 CMA-ES + 5 re-evaluations
        assert study._get_phases()[1].proposer._es.popsize == 4  # type: ignore[attr-defined]
    for options, message in [({"popsize": 1}, "popsize must be >= 2"), ({"pop": 4}, "has no option 'pop'"),
                              ({"popsize": "4"}, "popsize")]:  # fmt: skip
        with pytest.raises(ConfigError, match=message):
            build_config({"method": "cmaes", "method_options": options}, task=get_task("CartPole"))
    with pytest.raises(ConfigError, match="random takes no options"):
        build_config({"method": "random", "method_options": {"popsize": 4}}, task=get_task("CartPole"))


def test_stop_search_stops_the_study_and_it_can_be_finalized(tmp_path: Path) -> None:
    config = case_config("r2po")
    with Study.create(config, tmp_path / "r", llm=EchoOptimizer(config.llm)) as study:
        while study.store.candidate_count() < config.warmup:
            t = study.ask()
            study.tell(t, [1.0] * len(t.seeds), diagnostics=[{"episode_length": 1.0}] * len(t.seeds))
        proposer = study._get_phases()[1].proposer
        proposer.context_window = 10  # type: ignore[attr-defined]
        with pytest.raises(StopSearch, match="context overflow"):
            study.ask()
        assert study.status[0] is RunStatus.STOPPED and study.done
        with pytest.raises(StudyComplete, match="it stopped: context overflow"):
            study.ask()
        assert study.finalize() is not None and study.status[0] is RunStatus.STOPPED


# -- across processes ---------------------------------------------------------------------------
_ASK_AND_DIE = textwrap.dedent("""
    import json, os, signal, sys
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.study import Study
    class Slow(EchoOptimizer):
        def send(self, *a, **k):
            import time; time.sleep(float(sys.argv[3])); return super().send(*a, **k)
    with Study.load(sys.argv[1]) as s:
        llm = Slow(s.config.llm)
    with Study.load(sys.argv[1], llm=llm) as s:
        t = s.ask()
        print(json.dumps(t.to_json()), flush=True)
        if sys.argv[2] == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
""")


def _ask_in_process(run_dir: Path, mode: str, delay: float = 0.0) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.Popen([sys.executable, "-c", _ASK_AND_DIE, str(run_dir), mode, str(delay)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip


def _warm_up(study: Study) -> None:
    while study.store.candidate_count() < study.config.warmup:
        t = study.ask()
        r, c, d = _episodes(study, t.theta, t.seeds)
        study.tell(t, r, components=c, diagnostics=d)


def test_kill_between_ask_and_tell_then_ask_again_gives_the_same_trial(tmp_path: Path) -> None:
    config = case_config("pp-chat")
    with Study.create(config, tmp_path / "k", secrets=case_secrets("pp-chat", config), llm=EchoOptimizer(config.llm)) as study:
        _warm_up(study)
    proc = _ask_in_process(tmp_path / "k", "kill")
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGKILL, err
    asked = json.loads(out)
    with Study.load(tmp_path / "k", llm=EchoOptimizer(config.llm)) as study:
        again = study.ask()  # after the kill: the pending trial, no new LLM call
        assert again.number == asked["trial"] == config.warmup and again.theta.tolist() == asked["theta"]
        assert len(study.store.llm_calls()) == 1
        while not study.done:
            t = study.ask()
            r, c, d = _episodes(study, t.theta, t.seeds)
            study.tell(t, r, components=c, diagnostics=d)
        study.finalize()
        calls = study.store.llm_calls()
        cands = study.trials
    llm = [c for c in cands if c.source == "llm"]
    assert [c.index for c in cands] == list(range(config.warmup + config.iterations + 5))  # each candidate once (+ 5 re-evaluations)
    assert sorted(c["iteration"] for c in calls) == [c.iteration for c in llm]  # one LLM call per LLM candidate


def test_two_processes_asking_at_once_make_one_llm_call(tmp_path: Path) -> None:
    config = case_config("pp-chat")
    with Study.create(config, tmp_path / "t", secrets=case_secrets("pp-chat", config), llm=EchoOptimizer(config.llm)) as study:
        _warm_up(study)
    first = _ask_in_process(tmp_path / "t", "ask", delay=2.0)
    second = _ask_in_process(tmp_path / "t", "ask", delay=2.0)
    outs = [json.loads(p.communicate(timeout=120)[0]) for p in (first, second)]
    assert outs[0] == outs[1]  # the second waited for the first and got the same pending trial
    with open_store(tmp_path / "t") as store:
        assert len(store.llm_calls()) == 1 and store.pending_trial() is not None


def test_a_run_whose_process_died_does_not_show_as_running(tmp_path: Path) -> None:
    from ppprops.locks import RUNNING_LOCK, file_lock
    from ppprops.summary import run_summary

    config = case_config("random")
    with Study.create(config, tmp_path / "d") as study:
        study.store.set_status(RunStatus.RUNNING)  # as a process killed mid-run leaves it
    assert run_summary(tmp_path / "d")["status"] == "interrupted (no process is running it)"
    with file_lock(tmp_path / "d", RUNNING_LOCK):  # a process running it
        assert run_summary(tmp_path / "d")["status"] == "running"
