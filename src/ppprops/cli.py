"""The `ppprops` command. It alone turns PPPropsError into one line on stderr and exit code 2,
Ctrl-C into one line naming what to do next and exit code 130, and a closed stdout (``| head``)
into a quiet exit.

Public for other modules (the experiment specs build runs exactly as ``ppprops run`` does):
``build_parser``, ``run_parser`` (the ``run`` subcommand's parser) and ``run_config`` (parsed
``run`` flags to a RunConfig); ``commands`` (every subcommand with its one-line help) and
``parser_for`` (the parser of one command line).

A command line builds only the parser of the subcommand it names (``parser_for``): the settings
schema (pydantic), the tasks, the privacy and experiment modules load only for the subcommands
that use them, so ``ppprops --help``, ``ppprops ask`` and ``ppprops tell`` (a robot driven from
the shell calls the last two per trial) start fast. tests/test_startup.py keeps it so.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, NoReturn

from .errors import ConfigError, PPPropsError, interrupted_by_user
from .version import __version__

if TYPE_CHECKING:
    from .config import RunConfig

EXIT_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a command stopped by Ctrl-C
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: whoever read our output stopped reading (`| head`)


_NEGATIVE_NUMBER = re.compile(r"^-\.?\d")  # a value, not an option (_Parser)


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)  # --warm 2 is an error, not --warmup 2
        super().__init__(*args, **kwargs)
        # Values such as "-6,6" (--box) start like an option; argparse accepts only plain negative
        # numbers as values. Treat anything that starts with "-" and a digit (or "-." and a digit)
        # as a value, as Python 3.13's argparse does; no ppprops option looks like that.
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message: str) -> NoReturn:  # one line, exit 2 (argparse's default prints usage too)
        self.exit(EXIT_INPUT, f"ppprops: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``ppprops`` argument parser with every subcommand (run, resume, show, audit, report, ...)."""
    return _build_parsers()[0]


class Command(NamedTuple):
    """One subcommand of ``ppprops``: its one-line help (all that ``ppprops --help`` shows of it),
    what adds its arguments to its parser, and its handler (the exit code)."""

    help: str
    add: Callable[[argparse.ArgumentParser], None]
    handler: Callable[[argparse.Namespace], int]


def commands() -> dict[str, Command]:
    """The subcommands, in the order ``ppprops --help`` lists them. Made on each call (cheap: it
    imports nothing), so that a handler replaced on this module (a test's monkeypatch) is the one called."""
    return {
        "run": Command("start a search", _add_run, _cmd_run),
        "resume": Command("continue an interrupted run with its own secrets", _add_resume, _cmd_resume),
        "show": Command("summarise a run or study", _add_show, _cmd_show),
        "policy": Command("work with a policy file", _add_policy, _cmd_policy),
        "baseline": Command("train a standard baseline and store it as a run", _add_baseline, _cmd_baseline),
        "study": Command("a search driven from outside: create a study, retry a failed trial, finalize it (see ask, tell)", _add_study, _cmd_study),
        "ask": Command("the next trial of a study as one JSON object (exit 3: nothing more to ask; 4: --parallel trials are out)", _add_ask, _cmd_ask),
        "tell": Command("tell a study the feedback of a trial (raw values; flags for one episode, or JSON on stdin)", _add_tell,
                         _cmd_tell),  # fmt: skip
        "audit": Command("check every recorded request of a run or study for raw values (exit 0 clean; 1 leak, unverified or exposed)",
                          _one_of(_privacy_commands, "audit"), _cmd_audit),  # fmt: skip
        "privacy-report": Command("attacks x scheme (pp, pp-hardened) and their search results",
                                   _one_of(_privacy_commands, "privacy-report"), _cmd_privacy_report),  # fmt: skip
        "task": Command("work with a task: check a task file or env before a run", _one_of(_task_commands, "task"), _cmd_task),
        "experiment": Command("run a grid of tasks x methods x seeds (resumable), locally or on Ray",
                               _one_of(_experiment_commands, "experiment"), _cmd_experiment),  # fmt: skip
        "report": Command("tables, reward curves, history-cost plots and index.html from a grid directory",
                           _one_of(_experiment_commands, "report"), _cmd_report),  # fmt: skip
        "envs": Command("list the tasks", _add_envs, _cmd_envs),
    }


def _build_parsers(only: Collection[str] | None = None) -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The ``ppprops`` parser and its subcommands' parsers, by name. Every subcommand is listed
    (``ppprops --help``, the choices of an unknown command); only those in ``only`` (default: all)
    get their arguments."""
    p = _Parser(prog="ppprops", description="Privacy-preserving prompted policy search with an LLM as optimizer.")
    p.add_argument("--version", action="version", version=f"ppprops {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    parsers: dict[str, argparse.ArgumentParser] = {}
    for name, command in commands().items():
        parsers[name] = sub.add_parser(name, help=command.help)
        if only is None or name in only:
            command.add(parsers[name])
    return p, parsers


def _command_in(argv: Sequence[str]) -> str | None:
    """The subcommand argparse will run for ``argv``: its first argument that is not an option
    (``ppprops`` itself has only -h and --version, which take no value), or None."""
    for i, arg in enumerate(argv):
        if arg == "--":  # what follows is positional (Python 3.11's argparse takes "--" itself as the command)
            return argv[i + 1] if i + 1 < len(argv) else None
        if not arg.startswith("-") or _NEGATIVE_NUMBER.match(arg):
            return arg
    return None


def parser_for(argv: Sequence[str]) -> argparse.ArgumentParser:
    """The ``ppprops`` parser for the command line ``argv``: every subcommand is listed, and only
    the one ``argv`` names gets its arguments, so `ppprops ask DIR` costs no other subcommand's
    flags. It parses ``argv`` as ``build_parser()`` does."""
    return _build_parsers(only=(_command_in(argv) or "",))[0]


class _Into:
    """Stands in for the subparsers action that a module adding several subcommands at once takes
    (``privacy.commands.add_privacy_commands(sub, ...)``): the subcommand ``name`` gets ``parser``
    (made and listed by ``_build_parsers``), each other one a parser nobody keeps."""

    def __init__(self, name: str, parser: argparse.ArgumentParser) -> None:
        self.name = name
        self.parser = parser

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
        return self.parser if name == self.name else _Parser(prog=f"ppprops {name}")


def _one_of(add_commands: Callable[[Any], None], name: str) -> Callable[[argparse.ArgumentParser], None]:
    """What adds the arguments of ``name`` alone, of the subcommands ``add_commands(sub)`` adds together."""
    return lambda parser: add_commands(_Into(name, parser))


def _privacy_commands(sub: Any) -> None:
    from .privacy.commands import add_privacy_commands  # audit, privacy-report

    add_privacy_commands(sub, _Parser)


def _task_commands(sub: Any) -> None:
    from .tasks.commands import add_task_commands  # task check

    add_task_commands(sub, _Parser)


def _experiment_commands(sub: Any) -> None:
    from .experiments.cli import add_subcommands  # argparse only; grids load on use

    add_subcommands(sub)


def _add_run(r: argparse.ArgumentParser) -> None:
    add_run_flags(r)
    r.add_argument("--ray-address", default=None, metavar="ADDRESS",
                   help="evaluate each round's candidates as Ray tasks on this cluster (local: start Ray here; auto, "
                        "ray://head:10001); needs the ray extra")  # fmt: skip
    _audit_flag(r)


def _add_resume(rs: argparse.ArgumentParser) -> None:
    from .settings import add_flags

    rs.add_argument("dir", type=Path, help="the run directory (as `run` printed it)")
    ep = rs.add_argument_group("a corrected or different LLM endpoint (recorded in the run; the secrets stay the same)")
    add_flags(ep, only=ENDPOINT_KEYS, groups=None, help_suffix=" (default: the run's)")
    lim = rs.add_argument_group("the search's limits (stored with the run; a search that ended goes on when they leave room)")
    add_flags(lim, only=LIMIT_KEYS, groups=None, help_suffix=" (default: the run's)")
    rs.add_argument("--quiet", action="store_true", help="no progress on stderr")
    rs.add_argument("--json", action="store_true", help="print one JSON object (as `run --json`) on stdout")
    _audit_flag(rs)


def _add_show(sh: argparse.ArgumentParser) -> None:
    sh.add_argument("dir", type=Path, help="a run or study directory")
    sh.add_argument("--json", action="store_true", help="one JSON object with every candidate and LLM call")


def _add_policy(pol: argparse.ArgumentParser) -> None:
    polsub = pol.add_subparsers(dest="policy_command", required=True, parser_class=_Parser)
    pe = polsub.add_parser("eval", help="run a best_policy.json with no encoding involved")
    pe.add_argument("file", type=Path, help="a policy file (best_policy.json of a run), or a run or study directory")
    pe.add_argument("--episodes", type=int, default=20, help="episodes to run (default 20)")
    pe.add_argument("--seed", type=int, default=0,
                    help="seed of the fresh episode seeds; the run's seed and --final-episodes repeat its final evaluation (default 0)")
    pe.add_argument("--json", action="store_true", help="one JSON object (mean, std, every return) on stdout")
    pe.add_argument("--quiet", action="store_true", help="no progress on stderr")
    ps = polsub.add_parser("show", help="the best policy so far of a run or study directory (or a policy file) as one JSON object")
    ps.add_argument("path", type=Path, help="a run or study directory, or a policy file")


def _add_baseline(bl: argparse.ArgumentParser) -> None:
    from .methods import rl_algos

    blsub = bl.add_subparsers(dest="baseline_command", required=True, parser_class=_Parser)
    brl = blsub.add_parser("rl", help="a Stable-Baselines3 agent with the library's default hyperparameters (the rl extra)")
    brl.add_argument("--algo", required=True, choices=rl_algos(),
                     help="sac, td3, ddpg: continuous actions only; dqn: discrete only; ppo, a2c, trpo: both")
    brl.add_argument("--env", required=True, help="task name (see `ppprops envs`), e.g. Ant-Ultra, or a Gymnasium id")
    brl.add_argument("--timesteps", type=int, required=True, help="training timesteps (environment steps)")
    brl.add_argument("--seed", type=int, default=0, help="training seed, and the seed of the final evaluation's episodes (default 0)")
    brl.add_argument("--final-episodes", type=int, default=20, help="fresh episodes for the trained agent (default 20)")
    brl.add_argument("--out", type=Path, default=None, help="run directory (default runs/<task>__rl-<algo>__<seed>__<time>)")
    brl.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"], help="torch device (default cpu)")
    brl.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1: small MLPs gain nothing from more)")
    brl.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_study(st: argparse.ArgumentParser) -> None:
    from .study_commands import add_study_arguments  # study create, finalize

    add_study_arguments(st, _Parser, add_run_flags)


def _add_ask(ask: argparse.ArgumentParser) -> None:
    from .study_commands import add_ask_arguments

    add_ask_arguments(ask)


def _add_tell(tell: argparse.ArgumentParser) -> None:
    from .study_commands import add_tell_arguments

    add_tell_arguments(tell)


def _add_envs(en: argparse.ArgumentParser) -> None:
    from .settings import add_flags

    en.add_argument("--json", action="store_true", help="one JSON list of the tasks on stdout")
    add_flags(en, groups=None, only=("policy", "activation"), help_suffix="; D is given for it")


ENDPOINT_KEYS = ("base_url", "model", "api_key_env")  # the settings `resume` may change
LIMIT_KEYS = ("iterations", "target_return", "time_limit", "patience")  # and the search's limits


def add_run_flags(r: argparse.ArgumentParser) -> None:
    """The flags of ``ppprops run`` (``study create`` takes the same): every setting, ``--out``,
    ``--config``, ``--quiet`` and ``--json``."""
    from .settings import SETTINGS, add_flags

    add_flags(r, groups=None, only=[s.key for s in SETTINGS if s.group in ("task", "run")])
    r.add_argument("--out", type=Path, default=None,
                   help="run directory (default runs/<task>__<method>__<seed>__<time>-<id>, named by the run's id)")
    r.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="TOML or YAML file whose keys mirror these flags (env = \"CartPole\", top-k = 5, box = [-6, 6]); "
                        "flags given here win")  # fmt: skip
    add_flags(r, only=[s.key for s in SETTINGS if s.group not in ("task", "run")])
    r.add_argument("--quiet", action="store_true", help="no progress on stderr")
    r.add_argument("--json", action="store_true",
                   help="print one JSON object (the `show --json` summary, the run directory, the audit verdict) on stdout")


def _audit_flag(p: argparse.ArgumentParser) -> None:
    """``--audit quick|full|off`` of ``run`` and ``resume``: the audit printed at the end (a command option, not stored)."""
    from .privacy.commands import AUDIT_MODES

    p.add_argument("--audit", choices=AUDIT_MODES, default="quick",
                   help="the privacy audit of the run's last line: quick (default: no raw value sent, every request accounted "
                        "for; the attacks do not run), full (every attack too, as `ppprops audit DIR`), off")


def run_parser() -> argparse.ArgumentParser:
    """The parser of ``ppprops run``; its namespace holds only the settings given (``settings.given``)."""
    return _build_parsers(only=("run",))[1]["run"]


def run_config(a: argparse.Namespace, file_values: dict[str, Any] | None = None) -> RunConfig:
    """The RunConfig of parsed ``ppprops run`` flags, over ``file_values`` (a ``--config`` file's).

    Without ``--seed`` (on the command line or in the file) the run seed is drawn from the OS
    (``seeding.draw_seed``) and stored with the run (``--seed N`` repeats a run only with the same secrets: docs/experiments.md).

    Raises:
        ConfigError: one line naming the flag (``settings.build_config``).
    """
    from .settings import build_config, given, refuse_prompt_settings

    values = {**(file_values if file_values is not None else getattr(a, "file_settings", None) or {}), **given(a)}
    refuse_prompt_settings(str(values.get("method", "pp")), given(a))
    if "seed" not in values:
        from .seeding import draw_seed

        values["seed"] = draw_seed()
    return build_config(values)


def _say(text: str) -> None:
    """A line of progress on stderr (stdout is for results, and for `--json` only the JSON)."""
    print(text, file=sys.stderr, flush=True)


def _finished(run_dir: Path, as_json: bool, audit_mode: str = "quick") -> int:
    """What `run` and `resume` print at the end: the summary (or one JSON object) and the audit verdict
    (``--audit``: quick, full or off; ``privacy.commands.self_audit_line``)."""
    from .privacy.commands import self_audit_line
    from .summary import format_summary, run_summary

    summary = run_summary(run_dir)
    audit = self_audit_line(run_dir, audit_mode)  # the run checks its own transcript
    if as_json:
        print(json.dumps({**summary, "run_dir": str(run_dir), "privacy_audit": audit}))
    else:
        print(format_summary(summary))
        print(f"run directory: {run_dir}")
        print(audit)
    return 0


def _cmd_run(a: argparse.Namespace) -> int:
    from .naming import default_run_dir
    from .progress import ProgressEvents
    from .runner import check_startable, start

    config = run_config(a)
    out = a.out or default_run_dir(config)
    env = check_startable(config, out)  # every check that needs no episode, before anything is written or printed
    a.run_dir = out  # named by the Ctrl-C line
    fleet = None
    if a.ray_address:
        from .ray_fleet import RayFleet

        try:
            fleet = RayFleet(config.make_task(), a.ray_address)
        except BaseException:
            env.close()
            raise
    try:
        with ProgressEvents(enabled=not a.quiet, label=f"{config.task} {config.method}",
                            header=f"run directory: {out} (seed {config.seed})") as events:  # once the first episode passed
            start(config, out, events.hooks(), env=env, fleet=fleet)  # the run's episodes use the env the checks made
    finally:
        if fleet is not None:
            fleet.close()
    return _finished(out, a.json, a.audit)


def _cmd_resume(a: argparse.Namespace) -> int:
    from .baselines.record import refuse_resume
    from .progress import ProgressEvents
    from .runner import Endpoint, Limits, resume

    refuse_resume(a.dir)  # an RL baseline run has no search to continue
    a.run_dir = a.dir
    endpoint = Endpoint(**{key: getattr(a, key, None) for key in ENDPOINT_KEYS})
    limits = Limits(iterations=getattr(a, "iterations", None), target_return=getattr(a, "target_return", None),
                    time_limit_s=getattr(a, "time_limit", None), patience=getattr(a, "patience", None))  # fmt: skip
    with ProgressEvents(enabled=not a.quiet, label=str(a.dir)) as events:
        resume(a.dir, events.hooks(), endpoint=endpoint if endpoint.given else None, limits=limits if limits.given else None)
    return _finished(a.dir, a.json, a.audit)


def _cmd_show(a: argparse.Namespace) -> int:
    from .summary import format_summary, run_summary

    s = run_summary(a.dir)
    print(json.dumps(s) if a.json else format_summary(s))
    return 0


def _cmd_policy(a: argparse.Namespace) -> int:
    if a.policy_command == "show":
        from .study_commands import cmd_policy_show

        return cmd_policy_show(a)
    from .api import evaluate_policy
    from .rundir import DB_NAME, POLICY_NAME, is_run_dir, policy_path

    path = Path(a.file)
    if path.is_dir():
        if not is_run_dir(path):
            raise ConfigError(f"{path} is a directory but not a run or study directory (no {DB_NAME})")
        path = policy_path(path)
        if not path.exists():
            raise ConfigError(f"{a.file} has no {POLICY_NAME} yet: finish the run ('ppprops resume') or the study "
                              f"('ppprops study finalize {a.file}')")  # fmt: skip
    ev = evaluate_policy(path, episodes=a.episodes, seed=a.seed, progress=not a.quiet)
    result: dict[str, Any] = {"task": ev.task, "mean": ev.mean, "std": ev.std, "episodes": len(ev.returns), "seed": ev.seed,
                              "returns": list(ev.returns), "seeds": list(ev.seeds)}  # fmt: skip
    if a.json:
        print(json.dumps(result))
    else:
        print(f"{ev.task}: mean return {ev.mean:.2f} +- {ev.std:.2f} over {len(ev.returns)} episodes (seed {a.seed})")
    return 0


def _cmd_baseline(a: argparse.Namespace) -> int:
    from .baselines.rl import RLConfig, default_run_dir, run_baseline
    from .summary import format_summary, run_summary

    config = RLConfig(task=a.env, algo=a.algo, timesteps=a.timesteps, seed=a.seed, final_episodes=a.final_episodes,
                      device=a.device, threads=a.threads)  # fmt: skip
    config.validate()
    out = a.out or default_run_dir(config)
    a.run_dir = out  # named by the Ctrl-C line
    run_baseline(config, out, progress=not a.quiet)
    print(format_summary(run_summary(out)))
    print(f"run directory: {out}")
    return 0


def _cmd_envs(a: argparse.Namespace) -> int:
    from .tasks import list_tasks

    rows = [t.summary() for t in list_tasks()]
    given = getattr(a, "policy", None), getattr(a, "activation", None)
    if given != (None, None):
        from .policy import LINEAR, parse_policy

        try:
            policy = parse_policy(given[0] or LINEAR, given[1])
        except ValueError as e:
            raise ConfigError(str(e)) from None
        for r in rows:
            r["policy"], r["D"] = policy.label(), policy.param_count(r["n_s"], r["n_a"])
    if a.json:
        print(json.dumps(rows))
    else:
        for r in rows:
            family = "" if r["policy"] == "linear" else f" {r['policy']}"
            print(f"{r['name']:<18} {r['env_id']:<20} n_s={r['n_s']:<3} n_a={r['n_a']:<3} D={r['D']:<4} {r['action_type']}{family}")
    return 0


def _cmd_study(a: argparse.Namespace) -> int:
    from .study_commands import cmd_study

    return cmd_study(a, run_config)


def _cmd_ask(a: argparse.Namespace) -> int:
    from .study_commands import cmd_ask

    return cmd_ask(a)


def _cmd_tell(a: argparse.Namespace) -> int:
    from .study_commands import cmd_tell

    return cmd_tell(a)


def _cmd_audit(a: argparse.Namespace) -> int:
    from .privacy.commands import PRIVACY_HANDLERS

    return PRIVACY_HANDLERS["audit"](a)


def _cmd_privacy_report(a: argparse.Namespace) -> int:
    from .privacy.commands import PRIVACY_HANDLERS

    return PRIVACY_HANDLERS["privacy-report"](a)


def _cmd_task(a: argparse.Namespace) -> int:
    from .tasks.commands import TASK_HANDLERS

    return TASK_HANDLERS["task"](a)


def _cmd_experiment(a: argparse.Namespace) -> int:
    from .experiments.cli import cmd_experiment

    return cmd_experiment(a)


def _cmd_report(a: argparse.Namespace) -> int:
    from .experiments.cli import cmd_report

    return cmd_report(a)


COMMAND_KEYS = {"out": Path, "quiet": bool, "json": bool}  # `run` options a --config file may also hold


def _read_config_file(a: argparse.Namespace, path: Path) -> None:
    """Put a ``--config`` file's settings under the flags given: they go to ``a.file_settings``,
    and its ``out``/``quiet``/``json`` fill those options unless given on the command line."""
    from .config import read_table
    from .settings import read_settings

    table = read_table(path)
    where = f"config file {path}"
    for key, kind in COMMAND_KEYS.items():
        if key not in table:
            continue
        value = table.pop(key)
        if kind is bool and not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be true or false, got {value!r}")
        if kind is Path and not isinstance(value, str):
            raise ConfigError(f"{where}: {key} must be a string, got {value!r}")
        if not getattr(a, key):
            setattr(a, key, kind(value))
    a.file_settings = read_settings(table, where)


def interrupted_line(a: argparse.Namespace) -> str:
    """The one line printed on Ctrl-C: what was saved and the command that continues it."""
    from .store import DB_NAME

    run_dir: Path | None = getattr(a, "run_dir", None)
    if run_dir is None:
        return "ppprops: interrupted"
    if not (Path(run_dir) / DB_NAME).exists():
        return f"ppprops: interrupted before the run directory {run_dir} was created; nothing was saved"
    if a.command == "baseline":
        return f"ppprops: interrupted; the RL baseline in {run_dir} cannot be resumed: train it again with 'ppprops baseline rl'"
    return f"ppprops: interrupted; continue with 'ppprops resume {run_dir}'"


def _quiet_broken_pipe() -> int:
    """stdout's reader has gone (``ppprops show RUN | head -1``): say nothing more, and keep the
    interpreter's final flush from raising again, as the Python docs recommend."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return EXIT_BROKEN_PIPE


def main(argv: Sequence[str] | None = None) -> int:
    """The ``ppprops`` command: 0 on success, 2 on bad input (one line on stderr), 130 on Ctrl-C
    (one line naming the run directory to resume), 141 when stdout's reader stops reading;
    ``audit`` and ``experiment`` return 1 for a leak or a failed run."""
    parser = parser_for(sys.argv[1:] if argv is None else argv)
    try:
        return _main(parser, argv)
    except BrokenPipeError:
        return _quiet_broken_pipe()


def _main(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    try:
        args = parser.parse_args(argv)
    except PPPropsError as e:  # a plugin that fails to load while --method is checked (ppprops.plugins)
        print(f"ppprops: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    if getattr(args, "config", None) is not None and args.command in ("run", "study"):
        try:
            _read_config_file(args, args.config)
        except PPPropsError as e:
            print(f"ppprops: error: {e}", file=sys.stderr)
            return EXIT_INPUT
    try:
        code = commands()[args.command].handler(args)
        sys.stdout.flush()  # a closed pipe shows here, inside the handlers below, not at interpreter exit
        return code
    except PPPropsError as e:
        print(f"ppprops: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(interrupted_line(args), file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    except Exception as e:
        if not interrupted_by_user(e):  # a Ctrl-C that Python wrapped on its way up is still a Ctrl-C
            raise
        print(interrupted_line(args), file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
