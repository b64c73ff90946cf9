"""Warm starts (``ppprops.warm_start``): the given policies are the run's first trials, encoded
before any prompt shows them; the warm-up's other draws are those of a run without them; every
bad policy is one line, exit 2, nothing on disk."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import ppprops
from ppprops.cli import main
from ppprops.client.secrets import Secrets
from ppprops.errors import ConfigError
from ppprops.runner import start
from ppprops.store import open_store
from ppprops.wire.numbers import fmt_vector

from support import make_config

GIVEN = [1.234, -2.345, 0.5, 3.21, -0.77, 1.11, 2.22, -3.33, 0.44, 4.4]  # CartPole: n_s = 4, n_a = 2, D = 10
W = [GIVEN[0:2], GIVEN[2:4], GIVEN[4:6], GIVEN[6:8]]
B = GIVEN[8:10]


def _run(run: Path, init: tuple[tuple[float, ...], ...] = (), method: str = "random", **kw: object) -> list:
    config = replace(make_config("CartPole", method, warmup=4, iterations=2, final_episodes=0, seed=7, **kw),
                     init_policy=tuple("python" for _ in init), init_thetas=init)  # fmt: skip
    llm = None
    if method != "random":
        from ppprops.privacy.simulate import EchoOptimizer

        llm = EchoOptimizer(config.llm, spread=0.5)
    start(config, run, llm=llm, secrets=Secrets.generate("warm", 10, rng=np.random.default_rng(3)))
    with open_store(run) as store:
        return store.candidates()


def test_the_given_policies_come_first_and_the_warm_up_draws_after_them_are_unshifted(tmp_path: Path) -> None:
    plain = _run(tmp_path / "plain")
    other = [-v for v in GIVEN]
    warm = _run(tmp_path / "warm", init=(tuple(GIVEN), tuple(other)))
    assert [c.params.tolist() for c in warm[:2]] == [GIVEN, other]
    assert [c.source for c in warm] == ["init", "init", "warmup", "warmup", "random", "random"]
    assert [c.note for c in warm[:2]] == ["given policy 1", "given policy 2"]
    assert [c.params.tolist() for c in warm[2:4]] == [c.params.tolist() for c in plain[2:4]]  # draws 2 and 3, as without them


def test_a_given_policy_reaches_the_prompt_encoded_and_never_raw(tmp_path: Path) -> None:
    from ppprops.privacy.audit import audit_run

    run = tmp_path / "pp"
    cands = _run(run, init=(tuple(GIVEN),), method="pp")
    given = cands[0]
    assert given.source == "init" and given.params.tolist() == GIVEN
    with open_store(run) as store:
        requests = [c["request"] for c in store.llm_calls()]
    assert fmt_vector(list(given.params_enc), 2, digits=3, sep=",") in requests[0]  # shown, as its encoded values
    assert all(fmt_vector(GIVEN, 2, digits=3, sep=",") not in r for r in requests)
    assert all(f"{v:g}" not in r for r in requests for v in (1.234, -2.345, 3.21, -3.33))
    report = audit_run(run, attacks=False)
    assert not [f for f in report.findings if f.severity == "leak"], [f.to_json() for f in report.findings]


def _write(tmp_path: Path, name: str, doc: object) -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(doc), encoding="utf-8")
    return p


RUN = ["run", "--env", "CartPole", "--method", "random", "--warmup", "2", "--iterations", "1", "--final-episodes", "1",
       "--select-top", "0", "--quiet", "--audit", "off"]  # fmt: skip


def test_the_shell_takes_w_and_b_theta_and_a_policy_file_of_the_task(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    wb = _write(tmp_path, "wb.json", {"W": W, "b": B})
    theta = _write(tmp_path, "theta.json", {"theta": [-v for v in GIVEN]})
    assert main([*RUN, "--init-policy", str(wb), "--init-policy", str(theta), "--out", str(tmp_path / "a")]) == 0
    policy_file = tmp_path / "a" / "best_policy.json"
    assert main([*RUN, "--init-policy", str(policy_file), "--out", str(tmp_path / "b")]) == 0
    capsys.readouterr()
    with open_store(tmp_path / "a") as a, open_store(tmp_path / "b") as b:
        first = [c.params.tolist() for c in a.candidates()[:2]]
        best = json.loads(policy_file.read_text())["theta"]
        assert first == [GIVEN, [-v for v in GIVEN]] and b.candidates()[0].params.tolist() == best
        assert a.config()["init_policy"] == [str(wb), str(theta)]


def test_the_config_file_and_python_take_them(tmp_path: Path) -> None:
    wb = _write(tmp_path, "wb.json", {"W": W, "b": B})
    cfg = tmp_path / "run.toml"
    cfg.write_text(f'init-policy = ["{wb}"]\n', encoding="utf-8")
    assert main([*RUN, "--config", str(cfg), "--out", str(tmp_path / "c")]) == 0
    r = ppprops.search("CartPole", method="random", warmup=3, iterations=1, out=tmp_path / "p", evaluation={"final_episodes": 0},
                       init_policies=[wb, {"W": W, "b": B}, np.asarray(GIVEN) / 2])  # fmt: skip
    assert [c.params.tolist() for c in r.history[:3]] == [GIVEN, GIVEN, [v / 2 for v in GIVEN]]
    with ppprops.create_study("CartPole", method="random", warmup=2, iterations=1, storage=tmp_path / "s",
                              init_policies=[{"theta": GIVEN}]) as study:  # fmt: skip
        assert study.ask().theta.tolist() == GIVEN


@pytest.mark.parametrize(("doc", "line"), [
    ({"W": [[0.0, 0.0]] * 3, "b": [0.0, 0.0]}, "W must be 4x2 (one row per observation value) and b of length 2, got W of shape 3x2 "
                                                "and b of length 2"),
    ({"W": [[0.0] * 4, [0.0] * 4], "b": [0.0, 0.0]}, "W is 2x4, the transpose of what u = s @ W + b takes (4x2: one row per "
                                                      "observation value); an LQR gain K of u = -K s is W = -K^T"),
    ({"theta": [0.0] * 9}, "has 9 parameters; task CartPole has D = 10"),
    ({"theta": [float("nan")] + [0.0] * 9}, "theta holds nan, not a finite number"),
    ({"theta": [9.0] + [0.0] * 9}, "theta[0] = 9 lies outside the box -6,6 (1 of 10 values do): widen --box to hold it"),
    ({"W": W}, "needs W and b (u = s @ W + b), or theta"),
    ({"theta": GIVEN, "W": W, "b": B}, "gives theta and W/b: give one of them"),
    ({"format": "ppprops.linear_policy/2", "task": "Pendulum"}, "is a policy of task 'Pendulum', not of CartPole"),
    ([1, 2], "has 2 parameters; task CartPole has D = 10"),
    ("text", "must be a policy file, a JSON object with W and b or with theta, or D = 10 numbers"),
])  # fmt: skip
def test_a_bad_policy_is_one_line_and_leaves_nothing(doc: object, line: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, "bad.json", doc)
    assert main([*RUN, "--init-policy", str(path), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ppprops: error: --init-policy {path}") and err.count("\n") == 1, err
    assert line in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json"]


def test_a_missing_or_broken_file_and_too_many_policies_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.json"
    broken = tmp_path / "broken.json"
    broken.write_text("{W: 1", encoding="utf-8")
    ok = _write(tmp_path, "ok.json", {"theta": GIVEN})
    for args, line in (([str(missing)], f"--init-policy {missing}: no such file"),
                       ([str(broken)], f"--init-policy {broken} is not JSON (Expecting property name enclosed in double quotes at line 1)"),
                       ([str(ok)] * 3, "--init-policy: 3 policies given, more than the warm-up holds (--warmup 2)")):
        flags = [x for p in args for x in ("--init-policy", p)]
        assert main([*RUN, *flags, "--out", str(tmp_path / "r")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"ppprops: error: {line}") and err.count("\n") == 1, err
        assert not (tmp_path / "r").exists()
    with pytest.raises(ConfigError, match=r"^init policy has 3 parameters; task CartPole has D = 10"):
        ppprops.search("CartPole", method="random", warmup=2, iterations=1, out=tmp_path / "p", init_policies=[[1, 2, 3]])
    assert not (tmp_path / "p").exists()


# -- a study takes a policy at any time before its search is over --------------------------------------
def test_the_shell_enqueues_the_next_trial_in_the_place_of_a_warm_up_draw(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "study"
    policy = _write(tmp_path, "half.json", {"W": W, "b": B})
    assert main(["study", "create", "--env", "CartPole", "--method", "random", "--warmup", "3", "--iterations", "2", "--out", str(out)]) == 0
    assert main(["ask", str(out)]) == 0 and main(["tell", str(out), "0", "--return", "9"]) == 0
    capsys.readouterr()
    assert main(["study", "enqueue", str(out), str(policy)]) == 0
    assert capsys.readouterr().out == f"{policy} is queued: the next new trial 'ppprops ask {out}' hands out evaluates it\n"
    assert main(["ask", str(out)]) == 0
    trial = json.loads(capsys.readouterr().out)
    assert (trial["trial"], trial["source"], trial["theta"], trial["note"]) == (1, "init", GIVEN, "given policy half.json")
    assert main(["tell", str(out), "1", "--return", "30"]) == 0 and main(["ask", str(out)]) == 0
    third = json.loads(capsys.readouterr().out.splitlines()[-1])
    from ppprops.study import Study

    with Study.load(out) as study:  # the draw of trial 2 is warm-up draw 2 of this study's own stream, not draw 1
        warmup = study._get_phases()[0].proposer
        assert third["source"] == "warmup" and third["theta"] == warmup.ask(2).theta.tolist() != warmup.ask(1).theta.tolist()


def test_python_enqueues_w_and_b_mid_search_and_refuses_when_no_place_is_left(tmp_path: Path) -> None:
    with ppprops.create_study("CartPole", method="random", warmup=2, iterations=2, storage=tmp_path / "s",
                              evaluation={"select_top": 0}) as study:  # fmt: skip
        for _ in range(3):
            t = study.ask()
            study.tell(t, 10.0)
        assert study.enqueue(W=W, b=B) == 1  # the search's last place
        t = study.ask()
        assert (t.number, t.source, t.phase, t.theta.tolist()) == (3, "init", "random", GIVEN)
        with pytest.raises(ConfigError, match=r"^no place left for a given policy: its search is over$"):
            study.enqueue(GIVEN)
        with pytest.raises(ConfigError, match=r"^init policy has 2 parameters; task CartPole has D = 10"):
            study.enqueue([1.0, 2.0])
        study.tell(t, 20.0)
        assert study.done and study.store.queued() == []
    with ppprops.create_study("CartPole", method="cmaes", warmup=2, iterations=4, storage=tmp_path / "c",
                              evaluation={"select_top": 0}) as study:  # fmt: skip
        assert study.enqueue(GIVEN) == 1 and study.enqueue(GIVEN) == 2  # both warm-up places
        with pytest.raises(ConfigError, match=r"^no place left for a given policy: its warm-up is asked, and the method's search asks"):
            study.enqueue(GIVEN)
        assert [study.ask(worker=None).source] == ["init"]
