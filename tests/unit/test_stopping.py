"""Stop rules (``ppprops.stopping``): a target return, a time limit and patience end the search
early at the right candidate; the selection stage and the final evaluation still run, the reason is
stored and shown; bad values are one line with nothing on disk. Time comes from a fake clock."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from ppprops.cli import main
from ppprops.client.secrets import Secrets
from ppprops.errors import ConfigError
from ppprops.runner import start
from ppprops.stopping import StopRules, check, format_duration, parse_duration
from ppprops.store import open_store

from support import make_config

ROBOT = Path(__file__).resolve().parents[2] / "examples" / "robot_outside" / "robot.toml"


@pytest.mark.parametrize(("text", "seconds"), [("90s", 90.0), ("20m", 1200.0), ("2h", 7200.0), ("1h30m", 5400.0), ("1.5h", 5400.0),
                                               ("2d", 172800.0), ("45", 45.0), (45, 45.0), (2.5, 2.5), (" 20M ", 1200.0)])  # fmt: skip
def test_durations_read(text: object, seconds: float) -> None:
    assert parse_duration(text) == seconds


@pytest.mark.parametrize("text", ["5x", "", "h", "1h30", "m20", "-", "1 h x", True])
def test_a_bad_duration_names_the_forms(text: object) -> None:
    with pytest.raises(ValueError, match=r"^must be a duration such as 90s, 20m or 2h"):
        parse_duration(text)


def test_durations_print_as_they_read() -> None:
    assert [format_duration(s) for s in (5400, 90, 3.5, 7200, 1200, 61)] == ["1h30m", "1m30s", "3.5s", "2h", "20m", "1m1s"]
    assert all(parse_duration(format_duration(s)) == s for s in (5400, 90, 3.5, 7200, 86461))


def _cands(returns: list[float], warmup: int = 2) -> list[SimpleNamespace]:
    return [SimpleNamespace(index=i, ret=r, reevaluates=None, source="warmup" if i < warmup else "llm") for i, r in enumerate(returns)]


def test_each_rule_says_whether_it_fired_and_why() -> None:
    # warm-up 2 (5, 3); then 7 (better), 6, 7 (a tie is no improvement), 2, 1: the fourth in a row at candidate 6
    cands = _cands([5, 3, 7, 6, 7, 2, 1])
    for n, fired in ((3, True), (4, True), (5, False)):
        [verdict] = check(StopRules(patience=n), cands, elapsed_s=None)
        assert (verdict.rule, verdict.fired) == ("patience", fired)
        assert verdict.why == f"4 candidates in a row without a better return (patience {n})"
    [early] = check(StopRules(patience=4), cands[:6], elapsed_s=None)
    assert not early.fired  # three in a row at candidate 5
    [target] = check(StopRules(target_return=6.5), cands, elapsed_s=None)
    assert target.fired and target.why == "candidate 2's return 7 reached the target 6.5"
    [missed] = check(StopRules(target_return=8), cands, elapsed_s=None)
    assert not missed.fired and missed.why == "no return reached the target 8"
    nan = _cands([5, math.nan, 9], warmup=1)  # a numerical fault reaches nothing and improves nothing
    assert [c.fired for c in check(StopRules(target_return=6, patience=1), nan, elapsed_s=None)] == [True, False]
    clock = check(StopRules(time_limit_s=60), cands, elapsed_s=59.5) + check(StopRules(time_limit_s=60), cands, elapsed_s=60)
    assert [(c.rule, c.fired) for c in clock] == [("time_limit", False), ("time_limit", True)]
    assert check(StopRules(time_limit_s=60), cands, elapsed_s=None) == []  # not checked without the clock


def _run(tmp_path: Path, *, select_top: int = 0, **rules: object) -> tuple[Path, list, str, object]:
    config = replace(make_config("CartPole", "random", warmup=2, iterations=200, final_episodes=2, seed=3),
                     select_top=select_top, select_episodes=2, stop=StopRules(**rules))  # type: ignore[arg-type]
    run = tmp_path / "r"
    start(config, run, secrets=Secrets.generate("stop", 10, rng=np.random.default_rng(0)))  # CartPole: D = 10
    with open_store(run) as store:
        return run, store.candidates(), store.status(), store.final_eval()


def test_a_target_return_stops_at_the_first_candidate_reaching_it_then_selects_and_evaluates(tmp_path: Path) -> None:
    run, cands, status, fe = _run(tmp_path, select_top=2, target_return=30)
    search = [c for c in cands if c.reevaluates is None]
    hit = next(c for c in search if c.ret >= 30)
    assert hit.index < 201 and search[-1].index == hit.index  # nothing asked after it
    assert all(c.ret < 30 for c in search[:-1])
    reevals = [c for c in cands if c.reevaluates is not None]
    ranked = sorted(search, key=lambda c: (-c.ret, c.index))[:2]
    assert [c.reevaluates for c in reevals] == [c.index for c in ranked]  # the selection stage ran on the candidates told
    assert [c.index for c in reevals] == [hit.index + 1, hit.index + 2]
    assert status == f"stopped: target return reached after {hit.index + 1} candidates"
    assert fe is not None and len(fe.returns) == 2 and (run / "best_policy.json").is_file()
    s = _show_json(run)
    assert s["stop_reason"] == f"target return reached after {hit.index + 1} candidates"
    assert s["stop_rule"] == {"rule": "target_return", "why": f"candidate {hit.index}'s return {hit.ret:.6g} reached the target 30",
                              "end": hit.index + 1}  # fmt: skip


def test_patience_stops_after_exactly_n_candidates_without_improvement(tmp_path: Path) -> None:
    _, cands, status, fe = _run(tmp_path, patience=4)
    rets = [c.ret for c in cands]
    best_before = [max(rets[:i]) for i in range(1, len(rets))]
    streaks = []  # the run of search candidates (from 2, after the warm-up) not better than all before them
    for i in range(2, len(rets)):
        streaks.append(0 if rets[i] > best_before[i - 1] else (streaks[-1] if streaks else 0) + 1)
    assert streaks[-1] == 4 and 4 not in streaks[:-1]  # it stopped at the first candidate that made four
    assert status == f"stopped: patience of 4 candidates without a better return spent after {len(cands)} candidates"
    assert fe is not None


def test_the_time_limit_counts_on_the_search_clock(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ticks = itertools.count(1_000_000.0, 1.0)  # every reading of the clock is one second later
    monkeypatch.setattr("ppprops.study.time", lambda: next(ticks))
    _, cands, status, _ = _run(tmp_path, time_limit_s=10)
    # the clock starts with the run (0), then reads 1 s more at each ask and each tell: the ask at 10 s asks nothing
    assert len(cands) == 5 and status == "stopped: time limit 10s reached after 5 candidates"


def test_without_rules_nothing_is_written(tmp_path: Path) -> None:
    config = replace(make_config("CartPole", "random", warmup=2, iterations=3, final_episodes=0))
    start(config, tmp_path / "r", secrets=Secrets.generate("plain", 10, rng=np.random.default_rng(0)))
    with open_store(tmp_path / "r") as store:
        assert store.stop_state() == {} and store.status() == "finished" and "stop" not in store.config()


def _show_json(run: Path) -> dict:
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["show", str(run), "--json"]) == 0
    return json.loads(buf.getvalue())


RUN = ["run", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "5", "--final-episodes", "1", "--quiet",
       "--audit", "off"]  # fmt: skip


@pytest.mark.parametrize(("flags", "line"), [
    (["--time-limit", "5x"], "argument --time-limit: must be a duration such as 90s, 20m or 2h (or a number of seconds), got '5x'"),
    (["--time-limit", "0s"], "--time-limit must be a positive duration such as 90s, 20m or 2h, got 0 seconds"),
    (["--patience", "-1"], "--patience must be >= 1, got -1"),
    (["--target-return", "nan"], "--target-return must be a finite number, got nan"),
    (["--target-return", "inf"], "--target-return must be a finite number, got inf"),
])  # fmt: skip
def test_bad_stop_values_are_one_line_and_leave_nothing(flags: list[str], line: str, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    try:
        code = main([*RUN, *flags, "--out", str(tmp_path / "r")])
    except SystemExit as e:  # argparse refuses a flag's value itself
        code = e.code
    assert code == 2
    assert capsys.readouterr().err == f"ppprops: error: {line}\n"
    assert list(tmp_path.iterdir()) == []


def test_the_rules_are_config_file_keys_and_stored_with_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "run.toml"
    cfg.write_text('time-limit = "20m"\npatience = 3\ntarget-return = 500\n', encoding="utf-8")
    assert main([*RUN, "--config", str(cfg), "--out", str(tmp_path / "r")]) == 0
    assert _show_json(tmp_path / "r")["config"]["stop"] == {"target_return": 500.0, "time_limit_s": 1200.0, "patience": 3}
    cfg.write_text('time-limit = "soon"\n', encoding="utf-8")
    capsys.readouterr()
    assert main([*RUN, "--config", str(cfg), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "time-limit" in err and "must be a duration such as 90s, 20m or 2h" in err, err
    assert not (tmp_path / "s").exists()


def test_python_takes_the_rules_as_the_stop_group(tmp_path: Path) -> None:
    import ppprops

    r = ppprops.search("CartPole", method="random", warmup=2, iterations=50, out=tmp_path / "r", stop={"target_return": 9},
                       evaluation={"final_episodes": 1, "select_top": 0})  # fmt: skip
    hit = next(c for c in r.history if c.ret >= 9)
    assert r.status == f"stopped: target return reached after {hit.index + 1} candidate{'s' * (hit.index > 0)}"
    assert r.history[-1].index == hit.index
    with pytest.raises(ConfigError, match=r"^stop: unknown option 'patiance' \(did you mean patience\?\)$"):
        ppprops.search("CartPole", method="random", stop={"patiance": 3})


def test_a_study_asked_after_a_stop_says_why(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "study"
    assert main(["study", "create", "--task-file", str(ROBOT), "--method", "random", "--warmup", "2", "--iterations", "10",
                 "--target-return", "-50", "--out", str(out)]) == 0  # fmt: skip
    for number, ret in ((0, "-90"), (1, "-40")):
        assert main(["ask", str(out)]) == 0
        assert main(["tell", str(out), str(number), "--return", ret, "--component", f"reward_distance={ret}",
                     "--component", "reward_effort=0"]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["ask", str(out)]) == 3  # EXIT_DONE: nothing more to ask
    assert capsys.readouterr().err == (f"ppprops: study {out} has nothing more to ask (it stopped: target return reached after 2 "
                                       f"candidates); finalize it: 'ppprops study finalize {out}'\n")  # fmt: skip
    assert _show_json(out)["stop_reason"] == "target return reached after 2 candidates"  # open still, and says why it stopped
    assert main(["study", "finalize", str(out)]) == 0
    with open_store(out) as store:
        assert store.status() == "stopped: target return reached after 2 candidates" and store.candidate_count() == 2
    capsys.readouterr()
    assert main(["ask", str(out)]) == 3
    assert capsys.readouterr().err == f"ppprops: study {out} is finalized (2 of 2 trials told): nothing more to ask\n"


def test_a_time_limit_stops_a_run_of_a_hundred_thousand_iterations(tmp_path: Path) -> None:
    args = [*RUN, "--iterations", "100000", "--time-limit", "3s", "--select-top", "1", "--select-episodes", "1", "--out", str(tmp_path / "r")]
    assert main(args) == 0
    s = _show_json(tmp_path / "r")
    told = s["counts"]["candidates"] - 1  # the selection stage's one re-evaluation ran after the stop
    assert s["stop_reason"] == f"time limit 3s reached after {told} candidates" and 2 < told < 100_002
    assert s["counts"]["by_source"]["reeval"] == 1 and s["final_eval"] is not None


# -- resume with other limits: a search that ended goes on ---------------------------------------------
def _resume(run: Path, **limits: object) -> None:
    from ppprops.runner import Limits, resume

    resume(run, limits=Limits(**limits))  # type: ignore[arg-type]


def _state(run: Path) -> tuple[list, str, dict]:
    with open_store(run) as store:
        return store.candidates(), store.status(), store.stop_state()


def test_a_higher_target_on_resume_continues_after_the_selection_stage_which_stays(tmp_path: Path) -> None:
    run, first, _, _ = _run(tmp_path, select_top=2, target_return=30)
    end = next(c.index for c in first if c.ret >= 30) + 1
    best = max(c.ret for c in first if c.reevaluates is None)
    _resume(run, target_return=best + 1e-9)  # just above what was reached: the search goes on to beat it
    cands, status, state = _state(run)
    assert [(c.index, c.params.tolist(), c.ret) for c in cands[:end + 2]] == [(c.index, c.params.tolist(), c.ret) for c in first]
    assert state["stages"] == [[end, 2]]  # the first selection stage's two trials, kept where they were
    search = [c for c in cands if c.reevaluates is None]
    hit = next(c for c in search if c.ret > best)
    assert search[-1].index == hit.index > end + 1  # the search went on after the kept stage, to the first better return
    second = [c for c in cands if c.reevaluates is not None and c.index > hit.index]
    assert [c.index for c in second] == [hit.index + 1, hit.index + 2]  # and a selection stage of its own followed
    assert status == f"stopped: target return reached after {len(search)} candidates"
    again = {c.reevaluates: c.seeds for c in second} | {}
    firsts = {c.reevaluates: c.seeds for c in cands[end:end + 2]}
    assert all(again[k] != firsts[k] for k in again.keys() & firsts.keys())  # a candidate re-run in both stages: new seeds


def test_a_warm_up_cut_by_a_stop_goes_on_with_the_draws_it_would_have_made(tmp_path: Path) -> None:
    full = replace(make_config("CartPole", "random", warmup=8, iterations=2, final_episodes=0, seed=3), select_top=0)
    start(full, tmp_path / "full", secrets=Secrets.generate("stop", 10, rng=np.random.default_rng(0)))
    with open_store(tmp_path / "full") as store:
        plain = [c.params.tolist() for c in store.candidates()]
        rets = [c.ret for c in store.candidates()]
    target = max(rets[:8])  # the warm-up's best: reached inside the warm-up
    cut = replace(full, select_top=1, select_episodes=1, stop=StopRules(target_return=target))
    start(cut, tmp_path / "cut", secrets=Secrets.generate("stop", 10, rng=np.random.default_rng(0)))
    stopped = rets.index(target) + 1
    assert stopped < 8 and len(_state(tmp_path / "cut")[0]) == stopped + 1  # the cut warm-up, and its one re-evaluation
    _resume(tmp_path / "cut", target_return=1e9)
    cands, status, state = _state(tmp_path / "cut")
    drawn = [c.params.tolist() for c in cands if c.reevaluates is None]
    assert drawn == plain and state["stages"] == [[stopped, 1]] and status == "finished"  # no draw shifted by the stage between


def test_more_iterations_on_resume_continue_a_finished_run(tmp_path: Path) -> None:
    config = replace(make_config("CartPole", "random", warmup=2, iterations=3, final_episodes=1, seed=3), select_top=1, select_episodes=1)
    start(config, tmp_path / "r", secrets=Secrets.generate("more", 10, rng=np.random.default_rng(0)))
    _resume(tmp_path / "r", iterations=6)
    cands, status, state = _state(tmp_path / "r")
    assert [c.source for c in cands] == ["warmup"] * 2 + ["random"] * 3 + ["reeval"] + ["random"] * 3 + ["reeval"]
    assert state["stages"] == [[5, 1]] and status == "finished"
    with open_store(tmp_path / "r") as store:
        assert store.config()["iterations"] == 6


def test_a_larger_time_limit_and_patience_on_resume_continue(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ticks = itertools.count(1_000_000.0, 1.0)
    monkeypatch.setattr("ppprops.study.time", lambda: next(ticks))
    run, first, _, _ = _run(tmp_path, time_limit_s=10)
    assert len(first) == 5
    _resume(run, time_limit_s=20)
    cands, status, _ = _state(run)
    assert len(cands) == 10 and status == "stopped: time limit 20s reached after 10 candidates"  # 5 more in 10 more seconds


def test_limits_that_do_not_let_the_search_go_on_are_one_line_and_change_nothing(tmp_path: Path) -> None:
    from ppprops.runner import Limits, resume

    run, first, _, _ = _run(tmp_path, patience=3)
    db = (run / "run.sqlite").read_bytes()
    best = max(c.ret for c in first)
    cases = [
        ({"target_return": min(c.ret for c in first)}, "the search would stop again at once: candidate 0's return "),
        ({"patience": 2}, "the search would stop again at once: 3 candidates in a row without a better return (patience 2)"),
        ({"iterations": 1}, f"--iterations 1 is fewer than the {len(first) - 2} search candidates already asked"),
        ({"iterations": -1}, "--iterations must be >= 0, got -1"),
    ]
    for limits, line in cases:
        with pytest.raises(ConfigError) as e:
            resume(run, limits=Limits(**limits))  # type: ignore[arg-type]
        assert str(e.value).startswith(line), str(e.value)
        assert (run / "run.sqlite").read_bytes() == db
    assert best == max(c.ret for c in _state(run)[0])
    full = replace(make_config("CartPole", "random", warmup=2, iterations=2, final_episodes=0, seed=3))
    start(full, tmp_path / "f", secrets=Secrets.generate("f", 10, rng=np.random.default_rng(0)))
    with pytest.raises(ConfigError, match=r"^the search ran its whole budget \(--warmup 2, --iterations 2\): give a larger --iterations"):
        resume(tmp_path / "f", limits=Limits(patience=50))


def test_resume_takes_the_limits_from_the_shell_and_python(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import ppprops

    out = tmp_path / "r"
    assert main([*RUN, "--target-return", "9", "--iterations", "400", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["resume", str(out), "--target-return", "500.5", "--patience", "3", "--quiet", "--audit", "off"]) == 0
    s = _show_json(out)
    assert s["config"]["stop"] == {"target_return": 500.5, "time_limit_s": None, "patience": 3}
    assert s["stop_reason"].startswith("patience of 3 candidates without a better return spent after ")
    r = ppprops.resume(out, iterations=400, stop={"patience": 20})
    assert r.status.startswith("stopped: ") and len(r.history) > s["counts"]["candidates"]
    try:
        code = main(["resume", str(out), "--time-limit", "soon"])
    except SystemExit as e:
        code = e.code
    assert code == 2


# -- what a stop tells the provider --------------------------------------------------------------------
def _llm_run(tmp_path: Path, method: str, target: float) -> tuple[Path, list]:
    from ppprops.methods import resolve
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.tasks import get_task

    config = replace(make_config("CartPole", method, warmup=3, iterations=60, final_episodes=0, seed=5, mechanisms=resolve(method)),
                     stop=StopRules(target_return=target))  # fmt: skip
    D = get_task("CartPole").D
    secrets = (Secrets.generate_hardened("t", D, box=(-6.0, 6.0), reward_scale=500.0, rng=np.random.default_rng(4))
               if config.mechanisms.hardened else Secrets.generate("t", D, rng=np.random.default_rng(4)))  # fmt: skip
    run = tmp_path / method
    start(config, run, llm=EchoOptimizer(config.llm, spread=0.5), secrets=secrets)
    return run, _state(run)[0]


def test_the_audit_names_a_target_stop_under_pp_and_pp_hardened_delays_it_by_a_keyed_draw(tmp_path: Path) -> None:
    from ppprops.privacy.audit import audit_run
    from ppprops.stopping import keyed_delay
    from ppprops.study import Study

    run, cands = _llm_run(tmp_path, "pp", 60)
    hit = next(c for c in cands if c.ret >= 60)
    assert hit.source == "llm" and cands[-1].index == hit.index
    [found] = [f for f in audit_run(run, attacks=False).findings if f.kind == "stop_at_target"]
    assert found.severity == "channel" and found.locations == [f"candidate {hit.index}"]

    run, cands = _llm_run(tmp_path, "pp-hardened", 60)
    hit = next(c for c in cands if c.ret >= 60)
    with Study.load(run) as study:
        more = keyed_delay(study.streams, study.store)
        status = study.store.status()
    assert cands[-1].index == hit.index + more  # the search ran the keyed delay's candidates past the one that reached it
    assert status == f"stopped: target return reached after {hit.index + 1} candidates" + (f" (and {more} more, a keyed delay)" if more else "")
    report = audit_run(run, attacks=False)
    assert not [f for f in report.findings if f.kind == "stop_at_target"]
    assert f"stop: the target return ended the search {more} candidates after the one that reached it (a keyed delay)" in report.notes
