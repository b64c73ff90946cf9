"""The ask/tell commands, for a robot or simulator outside Python: ``ppprops study create``,
``ppprops ask``, ``ppprops tell``, ``ppprops study finalize`` and ``ppprops policy show``.

A process that never imports ppprops drives a search with them::

    ppprops study create --task-file robot.toml --method pp --out study/
    ppprops ask study/                 # one JSON object: trial, theta, W, b, seeds, ...
    ppprops tell study/ 0 --return 12.5 --component reward_dist=-3.2 --diagnostic reached=1
    ...                                # until `ppprops ask` exits with 3: nothing more to ask
    ppprops study finalize study/      # best_policy.json (and the final evaluation, with an env)

Several robots (or driver processes) evaluate trials side by side on a study created with
``--parallel P``: each asks with its own name (``ppprops ask DIR --worker robot-2``) and gets its
own trial (the same one again until it tells it); past P trials out, ``ask`` exits 4 with one line
saying which are out and who holds them, or waits with ``--wait``. A trial that could not be
evaluated is told ``--failed REASON``, and ``ppprops study retry DIR TRIAL`` asks it again.

Every error is one line on stderr and exit 2 (the main CLI turns ``PPPropsError`` into that), and
nothing is stored by a command that fails. ``ask`` exits 3 when the study has nothing more to ask.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import ConfigError, LLMError

if TYPE_CHECKING:
    from .values import Trial

EXIT_DONE = 3  # `ppprops ask` on a study with nothing more to ask
EXIT_WAIT = 4  # `ppprops ask` without --wait while --parallel trials are out (or a round waits for them)


def add_study_arguments(st: argparse.ArgumentParser, parser_class: type[argparse.ArgumentParser], add_run_flags: Any) -> None:
    """Add ``create`` and ``finalize`` to the main CLI's ``study`` parser ``st`` (the main CLI lists
    ``study``, ``ask`` and ``tell`` with their help, and adds the arguments of the one it runs).

    ``add_run_flags(parser)`` adds the flags of ``ppprops run`` (``study create`` takes the same).
    """
    stsub = st.add_subparsers(dest="study_command", required=True, parser_class=parser_class)
    cr = stsub.add_parser("create", help="create a study (the same flags as `run`); evaluate its trials with ask/tell")
    add_run_flags(cr)
    rt = stsub.add_parser("retry", help="ask a failed trial again (the same parameters and seeds, under its own number)")
    rt.add_argument("dir", type=Path, help="the study directory")
    rt.add_argument("trial", type=int, help="the number of the failed trial")
    eq = stsub.add_parser("enqueue", help="make a policy you have the next new trial asked (in its warm-up or search place)")
    eq.add_argument("dir", type=Path, help="the study directory")
    eq.add_argument("path", type=Path, help="a policy file of this task, or JSON with W and b (u = s @ W + b) or with theta")
    fi = stsub.add_parser("finalize", help="the final evaluation (with an env, or your own episodes) and best_policy.json")
    fi.add_argument("dir", type=Path, help="the study directory")
    fi.add_argument("--return", dest="returns", action="append", type=_finite_float, metavar="R", default=None,
                    help="the return of one final episode of the best policy on your robot (repeatable); "
                         "without it a task with an env runs its own final evaluation")  # fmt: skip
    fi.add_argument("--json", action="store_true", help="print the summary as one JSON object")


def add_ask_arguments(ask: argparse.ArgumentParser) -> None:
    """Add the arguments of ``ppprops ask`` to its parser."""
    ask.add_argument("dir", type=Path, help="the study directory")
    ask.add_argument("--worker", default=None, metavar="NAME",
                     help="who evaluates the trial (a plain name, e.g. robot-2): a worker gets its own trial again until it "
                          "tells it; with --parallel P, up to P workers hold a trial each")
    ask.add_argument("--wait", action="store_true",
                     help="when P trials are out (or a round waits for them), wait until one is told instead of exiting 4")


def add_tell_arguments(tell: argparse.ArgumentParser) -> None:
    """Add the arguments of ``ppprops tell`` to its parser."""
    tell.add_argument("dir", type=Path, help="the study directory")
    tell.add_argument("trial", type=int, help="the trial number `ppprops ask` printed")
    tell.add_argument("--worker", default=None, metavar="NAME", help="the worker that asked for the trial (checked: each worker "
                      "tells its own trials)")
    tell.add_argument("--failed", default=None, metavar="REASON",
                      help="the trial could not be evaluated (e.g. 'e-stop at 3.2 s'): kept with its reason, never shown to "
                           "the LLM nor selected; 'ppprops study retry' asks it again")
    tell.add_argument("--return", dest="returns", action="append", type=_finite_float, metavar="R", default=None,
                      help="the episode's return (raw reward units); repeat for several episodes")
    tell.add_argument("--component", action="append", default=[], metavar="NAME=VALUE",
                      help="a reward component's sum over the episode (repeatable; every declared component)")
    tell.add_argument("--diagnostic", action="append", default=[], metavar="NAME=VALUE",
                      help="a diagnostic's value (a number or a word; repeatable)")
    tell.add_argument("--stdin", action="store_true",
                      help='read the feedback as one JSON object from stdin: {"returns": [...], "components": [{...}], '
                           '"diagnostics": [{...}]} (one entry per episode) or {"return": R, "components": {...}, ...}')  # fmt: skip


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _pairs(items: list[str], what: str, *, numeric: bool) -> dict[str, float | str]:
    out: dict[str, float | str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ConfigError(f"--{what} must be NAME=VALUE, got {item!r}")
        name = name.strip()
        if name in out:
            raise ConfigError(f"--{what} {name} is given twice")
        try:
            number = float(value)
        except ValueError:
            if numeric:
                raise ConfigError(f"--{what} {name}={value!r}: expected a number") from None
            out[name] = value.strip()
            continue
        if not math.isfinite(number):
            raise ConfigError(f"--{what} {name}={value}: expected a finite number")
        out[name] = number
    return out


def _stdin_feedback() -> tuple[Any, Any, Any]:
    text = sys.stdin.read()
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"stdin is not a JSON object ({e.msg} at line {e.lineno})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"stdin must hold one JSON object, got {type(doc).__name__}")
    unknown = sorted(set(doc) - {"return", "returns", "components", "diagnostics"})
    if unknown:
        raise ConfigError(f"stdin: unknown key {unknown[0]!r} (known: return, returns, components, diagnostics)")
    if ("return" in doc) == ("returns" in doc):
        raise ConfigError('stdin: give "return" (one episode) or "returns" (a list, one per episode)')
    if isinstance(doc.get("return"), list):
        raise ConfigError('stdin: "return" is one episode\'s return; give several as "returns": [...]')
    if "returns" in doc and not isinstance(doc["returns"], list):
        raise ConfigError(f'stdin: "returns" must be a list, one return per episode, got {json.dumps(doc["returns"])}')
    returns = doc.get("return", doc.get("returns"))
    return returns, doc.get("components"), doc.get("diagnostics")


def cmd_ask(a: argparse.Namespace) -> int:
    """``ppprops ask DIR [--worker NAME] [--wait]``: print the worker's trial (the one it holds
    again, or a new one) as one JSON object.

    The embedded model is the study's warm server (``llm.embedded.WarmServer``): the first ask that
    needs it starts it, the next ones reuse it. Returns 0; ``EXIT_DONE`` (3) with one line on
    stderr when the study has nothing more to ask (its warm server, if any, then stops);
    ``EXIT_WAIT`` (4) with one line when ``--parallel`` trials are out and ``--wait`` is not given.
    Raises LLMError (exit 2, one line naming the study and the ask to repeat) when the endpoint
    stayed down past the retries.
    """
    _import_numpy()
    from .naming import check_worker

    worker = None if a.worker is None else check_worker(a.worker)
    trial = _stored_trial(a.dir, worker or "")
    if trial is not None:  # asked before and not yet told: the same trial again, from the store alone
        print(json.dumps(trial.to_json()))
        return 0
    from .llm.embedded import stop_warm_server
    from .study import Study, StudyComplete, TrialsOut

    with Study.load(a.dir, warm_llm=True) as study:
        try:
            trial = study.ask(worker, wait=a.wait)
        except StudyComplete as e:
            if not study.out:
                stop_warm_server(a.dir)
            print(f"ppprops: {e}" + ("" if e.finalized or study.out else f": 'ppprops study finalize {a.dir}'"), file=sys.stderr)
            return EXIT_DONE
        except TrialsOut as e:
            print(f"ppprops: {e} (ask again later, or with --wait)", file=sys.stderr)
            return EXIT_WAIT
        except LLMError as e:  # nothing was stored for it: the next ask asks the LLM again
            raise LLMError(f"{e}; the study is kept: ask again once the endpoint answers ('ppprops ask {a.dir}')") from None
        print(json.dumps(trial.to_json()))
    return 0


BLAS_THREAD_TIMEOUT = "OPENBLAS_THREAD_TIMEOUT"


def _import_numpy() -> None:
    """Import numpy with OpenBLAS's worker threads told to sleep as soon as they are idle
    (``OPENBLAS_THREAD_TIMEOUT=4``: 2^4 cycles; unless the environment sets it).

    By default each worker thread spins for 2^28 cycles after OpenBLAS starts, about 0.1 s of
    another core's time in every process that imports numpy (more than numpy's own import), which
    ``ppprops ask`` and ``ppprops tell``, one process each per trial and no BLAS work, would pay in
    full. A BLAS call still runs on every thread (it wakes them), and results do not change. The
    variable is set only while numpy loads, when OpenBLAS reads it, so no process started later
    (an env worker, the embedded model) inherits it.
    """
    if "numpy" in sys.modules or BLAS_THREAD_TIMEOUT in os.environ:
        import numpy  # noqa: F401

        return
    os.environ[BLAS_THREAD_TIMEOUT] = "4"
    try:
        import numpy  # noqa: F401
    finally:
        del os.environ[BLAS_THREAD_TIMEOUT]


def _stored_trial(run_dir: Path, worker: str = "") -> Trial | None:
    """The pending trial ``worker`` holds (asked for, not yet told), as ``Study.ask`` returns it first, read
    from the store under the study's lock, after the key file is checked against the store as
    ``Study.load`` checks it; None when there is none, or when anything fails (``cmd_ask`` then
    loads the study, which says what in its own words).

    Nothing else is built (no task, codec, proposer or LLM client: numpy and SQLite only), so a
    robot asking again (after a restart, or twice per trial) pays for no more. What ``Study.load``
    also checks and this does not, the stored configuration, task and method, was checked when the
    trial was asked, and ``tell`` checks it again.
    """
    from .client.secrets import Secrets
    from .locks import STUDY_LOCK, file_lock
    from .rundir import KEY_NAME
    from .store import DB_NAME, open_store

    if not (Path(run_dir) / DB_NAME).exists():
        return None
    try:
        with open_store(run_dir) as store, file_lock(run_dir, STUDY_LOCK):
            trial = next((t for t in store.pending_trials() if t.worker == worker), None)
            if trial is None:
                return None
            family = ((store.config().get("task_spec") or {}).get("policy") or {}).get("kind", "linear")
            linear_D = (trial.n_s + 1) * trial.n_a  # the linear policy's D (Eq. 10)
            if family != "linear" or len(trial.theta) != linear_D:
                return None  # an MLP's trial: the full path knows its layers (the study's policy family)
            Secrets.load(Path(run_dir) / KEY_NAME, run_id=store.run_id(), D=linear_D,
                             fingerprint=store.key_fingerprint())  # fmt: skip
            return trial
    except Exception:  # whatever it is, the full path meets it too and says it as it always has
        return None


def cmd_tell(a: argparse.Namespace) -> int:
    """``ppprops tell DIR TRIAL ...``: record a trial's raw feedback; prints one line (the
    candidate's return and the best so far). Errors store nothing. After the last trial the
    study's warm server (``cmd_ask``), if any, stops."""
    _import_numpy()
    from .study import Study

    if a.failed is not None:
        if a.returns or a.component or a.diagnostic or a.stdin:
            raise ConfigError("--failed says the trial could not be evaluated: give no --return, --component, --diagnostic or --stdin with it")
        if not a.failed.strip():
            raise ConfigError("--failed needs a reason (what went wrong, e.g. --failed 'e-stop at 3.2 s')")
        with Study.load(a.dir) as study:
            study.tell(a.trial, failed=a.failed, worker=a.worker)
            told, failed, total = study.store.candidate_count(), study.store.failed_count(), study.total
        print(f"trial {a.trial}: failed ({' '.join(a.failed.split())}); {told} of {total} told, {failed} failed "
              f"(ask it again: ppprops study retry {a.dir} {a.trial})")
        return 0
    if a.stdin:
        if a.returns or a.component or a.diagnostic:
            raise ConfigError("--stdin reads everything from stdin: give no --return, --component or --diagnostic with it")
        returns, components, diagnostics = _stdin_feedback()
    else:
        if not a.returns:
            raise ConfigError("tell needs --return R (or --stdin with a JSON object)")
        if len(a.returns) > 1 and (a.component or a.diagnostic):
            raise ConfigError("several --return values with --component/--diagnostic: give one episode's values per call, "
                              "or the whole feedback as JSON with --stdin")  # fmt: skip
        returns = a.returns if len(a.returns) > 1 else a.returns[0]
        components = _pairs(a.component, "component", numeric=True)
        diagnostics = _pairs(a.diagnostic, "diagnostic", numeric=False)
    with Study.load(a.dir) as study:
        cand = study.tell(a.trial, returns, components=components, diagnostics=diagnostics, worker=a.worker)
        best = study.best
        told, total = study.store.candidate_count(), study.total
        if study.done:
            from .llm.embedded import stop_warm_server  # the embedded model's client: only after the last trial

            stop_warm_server(a.dir)
    best_text = f"; best {best.ret:.4g} (trial {best.index})" if best is not None else ""
    print(f"trial {cand.index}: return {cand.ret:.4g}{best_text}; {told} of {total} told")
    return 0


def cmd_study(a: argparse.Namespace, run_config: Any) -> int:
    """``ppprops study create`` / ``enqueue`` / ``retry`` / ``finalize``."""
    from .study import Study

    if a.study_command == "create":
        from .naming import default_run_dir
        from .runner import check_creatable

        config = run_config(a)
        out = a.out or default_run_dir(config)
        check_creatable(config, Path(out))  # a study that cannot start leaves nothing
        a.run_dir = out
        with Study.create(config, out) as study:
            print(json.dumps({"dir": str(out), "task": study.task.name, "method": study.method.name, "seed": config.seed,
                              "trials": study.total, "D": study.task.D}) if a.json else f"study directory: {out}")
        return 0
    if a.study_command == "enqueue":
        from .warm_start import init_thetas

        with Study.load(a.dir) as study:
            [theta] = init_thetas([a.path], study.task, box=study.config.box, warmup=1, flag="")
            place = study.enqueue(theta, note=f"given policy {a.path.name}")
        ahead = f" ({place - 1} queued before it)" if place > 1 else ""
        print(f"{a.path} is queued{ahead}: the next new trial 'ppprops ask {a.dir}' hands out evaluates it")
        return 0
    if a.study_command == "retry":
        with Study.load(a.dir) as study:
            again = study.retry(a.trial)
        print(f"trial {again.number} is pending again (the same parameters and seeds): the next 'ppprops ask {a.dir}' hands it out")
        return 0
    from .summary import format_summary, run_summary

    with Study.load(a.dir) as study:
        told, failed, total = study.store.candidate_count(), study.store.failed_count(), study.total
        study.finalize(returns=a.returns)
    lost = f", {failed} failed (never selected)" if failed else ""
    if told + failed < total:  # stopping early is the user's call; say what it means once
        print(f"ppprops: note: study finalized after {told} of its {total} planned trials{lost}; its best of those is handed "
              "over (nothing more can be asked)", file=sys.stderr)
    elif failed:
        print(f"ppprops: note: study finalized with {told} of its {total} trials told and {failed} failed (never selected, not "
              "retried); its best told trial is handed over", file=sys.stderr)
    s = run_summary(a.dir)
    print(json.dumps(s) if a.json else format_summary(s))
    return 0


def cmd_policy_show(a: argparse.Namespace) -> int:
    """``ppprops policy show DIR|FILE``: the best policy so far of a run or study directory (or a
    policy file) as one JSON object: W, b, theta, the observation and action rules."""
    from .policy_file import load_policy
    from .rundir import DB_NAME, is_run_dir

    path = Path(a.path)
    if path.is_dir() and not is_run_dir(path):
        raise ConfigError(f"{path} is not a ppprops run directory (no {DB_NAME}) nor a policy file")
    if path.is_dir():
        from .study import Study

        with Study.load(path) as study:
            doc = study.policy_document()
    else:
        doc = load_policy(path).document
    print(json.dumps(doc))
    return 0
