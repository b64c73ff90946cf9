"""The `ppprops` command. It alone turns PPPropsError into one line on stderr and exit code 2,
Ctrl-C into one line naming what to do next and exit code 130, and a closed stdout (``| head``)
into a quiet exit.

Public for other modules (the experiment specs build runs exactly as ``ppprops run`` does):
``build_parser``, ``run_parser`` (the ``run`` subcommand's parser) and ``run_config`` (parsed
``run`` flags to a RunConfig).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from . import __version__
from .config import PROMPT_FORMS, PROMPT_LAYOUTS, PROMPT_PARAMS, REASONING_EFFORTS, LLMConfig, RunConfig
from .errors import PPPropsError
from .methods import SWITCHES, get_method, rl_algos, search_method_names, switch_flag

EXIT_INPUT = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report a command stopped by Ctrl-C
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: whoever read our output stopped reading (`| head`)


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # Values such as "-6,6" (--box) start like an option; argparse accepts only plain negative
        # numbers as values. Treat anything that starts with "-" and a digit (or "-." and a digit)
        # as a value, as Python 3.13's argparse does; no ppprops option looks like that.
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str) -> NoReturn:  # one line, exit 2 (argparse's default prints usage too)
        self.exit(EXIT_INPUT, f"ppprops: error: {message}\n")


def _box(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH, got {text!r}") from None
    return lo, hi


def _json_object(text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"expected a JSON object such as '{{\"g\": 9.81}}', got {text!r} ({e.msg})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object such as '{{\"g\": 9.81}}', got {text!r}")
    return value


_json_object.accepts_table = True  # type: ignore[attr-defined]  # a --config file may give a TOML table


def _names(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"expected K1,K2,..., got {text!r}")
    return names


def _flag(value: str) -> bool:
    if value.lower() in ("on", "true", "yes", "1"):
        return True
    if value.lower() in ("off", "false", "no", "0"):
        return False
    raise argparse.ArgumentTypeError(f"expected on or off, got {value!r}")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ppprops", description="Privacy-preserving prompted policy search with an LLM as optimizer.")
    p.add_argument("--version", action="version", version=f"ppprops {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    r = sub.add_parser("run", help="start a search")
    r.add_argument("--env", default=None,
                   help="task name (see `ppprops envs`), a Gymnasium id, module:EnvId, or module:attr (an env class or factory)")
    r.add_argument("--task-file", type=Path, default=None, metavar="FILE",
                   help="a task described in TOML (env, observation, feedback keys, prose; docs/own-robot.md) instead of --env")
    r.add_argument("--env-kwargs", type=_json_object, default=None, metavar="JSON",
                   help="keyword arguments of the env's constructor, as a JSON object")
    r.add_argument("--max-episode-steps", type=int, default=None, metavar="N",
                   help="time limit of an episode (needed when the env has none of its own)")
    r.add_argument("--gym-packages", action="append", default=[], metavar="MOD",
                   help="a module to import first, e.g. one that registers the env (repeatable)")
    r.add_argument("--obs-keys", type=_names, default=None, metavar="K1,K2",
                   help="a Dict observation: the entries the policy sees, in this order")
    r.add_argument("--method", choices=search_method_names(), default="pp",
                   help="a preset of the paper (default pp), R2PO, or a black-box baseline at the same budget")
    r.add_argument("--warmup", type=int, default=10, help="random warm-up policies (default 10)")
    r.add_argument("--iterations", type=int, default=50,
                   help="LLM iterations (default 50); r2po: LLM calls, two per two-stage iteration; random, cmaes: samples")
    r.add_argument("--top-k", type=int, default=10, help="history entries in the prompt; 0 = all (default 10)")
    r.add_argument("--episodes", type=int, default=None, help="episodes per candidate (default 1; 20 for r2po)")
    r.add_argument("--final-episodes", type=int, default=20, help="fresh episodes for the best policy (default 20)")
    r.add_argument("--seed", type=int, default=0, help="run seed: warm-up, episode seeds, LLM sampling seeds (default 0)")
    r.add_argument("--out", type=Path, default=None, help="run directory (default runs/<task>__<method>__<seed>__<time>)")
    r.add_argument("--box", type=_box, default=(-6.0, 6.0), metavar="LOW,HIGH",
                   help="feasible range of every parameter (default -6,6)")
    r.add_argument("--decimals", type=int, default=2, help="decimals of numbers in the prompt (default 2)")
    r.add_argument("--prompt-params", choices=PROMPT_PARAMS, default="list",
                   help="history parameters as one list (default, compact) or as ProPS-style params[i]: value pairs")
    r.add_argument("--param-digits", type=int, default=None,
                   help="significant digits of each parameter, at most --decimals decimals; 0 = fixed decimals "
                        "(default 3 in the chat form's list, 2 in the document form)")
    r.add_argument("--prompt-layout", choices=PROMPT_LAYOUTS, default="static-first",
                   help="fixed sections before the history (default; a server's prefix cache reuses them) or history first")
    r.add_argument("--prompt-form", choices=PROMPT_FORMS, default="auto",
                   help="chat: the paper's instruction prompt; document: the history as a document for a base model "
                        "to continue (completions endpoint); auto (default): document for the embedded model, chat otherwise")
    r.add_argument("--workers", type=int, default=1, help="processes running episodes in parallel (default 1)")
    r.add_argument("--component", action="append", default=[], metavar="KEY",
                   help="an info key to sum as a reward component (repeatable); KEY.SUB picks an entry of a dict, KEY.* all")
    r.add_argument("--diagnostic", action="append", default=[], metavar="KEY",
                   help="an info key to report as a diagnostic (its last value; repeatable)")
    r.add_argument("--parse-retries", type=int, default=2, help="corrections asked for before a fallback (default 2)")
    r.add_argument("--on-llm-failure", choices=["stop", "skip"], default="stop",
                   help="when the endpoint stays down past --retries: stop, resumable (default), or skip: "
                        "record a fallback candidate and go on")
    r.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="TOML file whose keys mirror these flags (env = \"CartPole\", top-k = 5, box = [-6, 6]); flags given here win")
    g = r.add_argument_group("mechanisms (override the preset one by one)")
    for name in SWITCHES:  # hardening switches: docs/threat-model.md
        g.add_argument(switch_flag(name), type=_flag, default=None, metavar="on|off", help=SWITCH_HELP[name])
    llm = r.add_argument_group("LLM endpoint (default: the embedded Gemma 3 270M, offline)")
    _endpoint_flags(llm)
    llm.add_argument("--temperature", type=float, default=None,
                     help="sampling temperature, 0 to 2 (default: 1.0 for the chat form; the document form alternates 0.6 and 1.0)")
    llm.add_argument("--max-tokens", type=int, default=None,
                     help="answer token budget; reasoning counts against it (default: room for D numbers, "
                          "plus room for reasoning when --reasoning-effort is set or the endpoint reasons)")
    llm.add_argument("--timeout", type=float, default=300.0, help="seconds per request (default 300)")
    llm.add_argument("--reasoning-effort", default=None, choices=REASONING_EFFORTS,
                     help="for reasoning models (gpt-oss, OpenAI o-series); none turns thinking off on Ollama's /v1")
    llm.add_argument("--structured", default="auto", choices=["auto", "json_schema", "grammar", "none"],
                     help="constrained output: auto = grammar for the embedded model, JSON schema otherwise")
    llm.add_argument("--context-size", type=int, default=16384, help="embedded model context (default 16384)")
    llm.add_argument("--retries", type=int, default=4,
                     help="retries of one request after a timeout, refused or dropped connection, 429 or 5xx (default 4)")
    llm.add_argument("--retry-base-delay", type=float, default=1.0, metavar="S",
                     help="first backoff in seconds, doubled per retry, with jitter (default 1)")
    llm.add_argument("--retry-max-delay", type=float, default=30.0, metavar="S", help="longest backoff in seconds (default 30)")
    llm.add_argument("--retry-after-cap", type=float, default=60.0, metavar="S",
                     help="longest Retry-After of a 429 that is honoured, seconds (default 60)")
    r.add_argument("--quiet", action="store_true", help="no progress on stderr")
    r.add_argument("--json", action="store_true",
                   help="print one JSON object (the `show --json` summary, the run directory, the audit verdict) on stdout")

    rs = sub.add_parser("resume", help="continue an interrupted run with its own secrets")
    rs.add_argument("dir", type=Path, help="the run directory (as `run` printed it)")
    ep = rs.add_argument_group("a corrected or different LLM endpoint (recorded in the run; the secrets stay the same)")
    _endpoint_flags(ep, resume=True)
    rs.add_argument("--quiet", action="store_true", help="no progress on stderr")
    rs.add_argument("--json", action="store_true", help="print one JSON object (as `run --json`) on stdout")

    sh = sub.add_parser("show", help="summarise a run")
    sh.add_argument("dir", type=Path, help="a run directory")
    sh.add_argument("--json", action="store_true", help="one JSON object with every candidate and LLM call")

    pol = sub.add_parser("policy", help="work with a policy file")
    polsub = pol.add_subparsers(dest="policy_command", required=True, parser_class=_Parser)
    pe = polsub.add_parser("eval", help="run a best_policy.json with no encoding involved")
    pe.add_argument("file", type=Path, help="a policy file (best_policy.json of a run)")
    pe.add_argument("--episodes", type=int, default=20, help="episodes to run (default 20)")
    pe.add_argument("--seed", type=int, default=0,
                    help="seed of the fresh episode seeds; the run's seed and --final-episodes repeat its final evaluation (default 0)")
    pe.add_argument("--json", action="store_true", help="one JSON object (mean, std, every return) on stdout")
    pe.add_argument("--quiet", action="store_true", help="no progress on stderr")

    bl = sub.add_parser("baseline", help="train a standard baseline and store it as a run")
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

    from .privacy.commands import add_privacy_commands  # audit, privacy-report

    add_privacy_commands(sub, _Parser)

    from .experiments.cli import add_subcommands as add_experiment_subcommands  # argparse only; grids load on use

    add_experiment_subcommands(sub, run_parser=r)

    en = sub.add_parser("envs", help="list the tasks")
    en.add_argument("--json", action="store_true", help="one JSON list of the tasks on stdout")
    return p


SWITCH_HELP = {
    "encode_params": "parameters shown as A theta (Sec. II-B)",
    "scale_rewards": "returns and reward components shown as c r (Sec. II-C)",
    "detailed_feedback": "reward components and diagnostics in the history",
    "disclose_optimum": "state the optimal return as a target (Vanilla ProPS)",
    "disclose_reward_structure": "state the numeric reward definition",
    "describe_task": "task description in the prompt: on = ProPS+, off = ProPS (policy structure only)",
    "secret_offsets": "hardening: secret raw origins, A (theta - m) and c (r - s)",
    "warp_params": "hardening: the box mapped onto the real line before A",
    "warp_rewards": "hardening: a secret increasing power warp of the rewards",
    "hide_return_diagnostics": "hardening: drop diagnostics that pin the return",
    "encoded_warmup": "hardening: warm-up drawn in the encoded space",
}


def _endpoint_flags(group: Any, *, resume: bool = False) -> None:
    """--base-url, --model, --api-key-env: for `run`, and for `resume` against another endpoint."""
    keep = " (default: the run's)" if resume else ""
    group.add_argument("--base-url", default=None,
                       help=f"OpenAI-compatible API root that /chat/completions (/completions: document form) is appended to, e.g. http://localhost:11434/v1{keep}")  # fmt: skip
    group.add_argument("--model", default=None, help=f"model name at that endpoint (required with --base-url){keep}")
    group.add_argument("--api-key-env", default=None, metavar="VAR",
                       help=f"environment variable that holds the API key (never stored){keep}")  # fmt: skip


def run_parser() -> argparse.ArgumentParser:
    """The parser of ``ppprops run`` (its actions list every run setting and its checks)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["run"]  # type: ignore[no-any-return]


def run_config(a: argparse.Namespace) -> RunConfig:
    """The RunConfig of parsed ``ppprops run`` flags (``run_parser().parse_args(...)``).

    The method's registry entry gives its mechanisms (preset plus the on/off flags given) and
    its default episodes. Raises ConfigError for a missing --env, an unknown task, or a
    mechanism the method refuses; ``RunConfig.validate`` checks the numbers.
    """
    if a.env is None and getattr(a, "task_file", None) is None:
        from .errors import ConfigError

        raise ConfigError("--env or --task-file is required (on the command line, or in the --config file)")
    method = get_method(a.method)
    mech = method.mechanisms(**{name: getattr(a, name) for name in SWITCHES})
    from .tasks import is_builtin, load_task

    task = load_task(a.env, task_file=getattr(a, "task_file", None), env_kwargs=getattr(a, "env_kwargs", None),
                     max_episode_steps=getattr(a, "max_episode_steps", None), gym_packages=getattr(a, "gym_packages", ()),
                     obs_keys=getattr(a, "obs_keys", None), components=a.component, diagnostics=a.diagnostic)  # fmt: skip
    return RunConfig(
        task=task.name,
        task_spec=None if is_builtin(task) or task.spec is None else task.spec.to_json(),
        workers=a.workers,
        method=a.method,
        mechanisms=mech,
        warmup=a.warmup,
        iterations=a.iterations,
        top_k=a.top_k,
        episodes=a.episodes if a.episodes is not None else method.default_episodes,
        final_episodes=a.final_episodes,
        seed=a.seed,
        box=a.box,
        decimals=a.decimals,
        prompt_params=a.prompt_params,
        param_digits=a.param_digits,
        prompt_layout=a.prompt_layout,
        prompt_form=a.prompt_form,
        parse_retries=a.parse_retries,
        on_llm_failure=a.on_llm_failure,
        llm=LLMConfig(
            base_url=a.base_url,
            model=a.model,
            api_key_env=a.api_key_env,
            temperature=a.temperature,
            max_tokens=a.max_tokens,
            timeout_s=a.timeout,
            reasoning_effort=a.reasoning_effort,
            structured=a.structured,
            context_size=a.context_size,
            transport_retries=a.retries,
            retry_base_s=a.retry_base_delay,
            retry_max_s=a.retry_max_delay,
            retry_after_cap_s=a.retry_after_cap,
        ),
    )


def _say(text: str) -> None:
    """A line of progress on stderr (stdout is for results, and for `--json` only the JSON)."""
    print(text, file=sys.stderr, flush=True)


def _finished(run_dir: Path, as_json: bool) -> int:
    """What `run` and `resume` print at the end: the summary (or one JSON object) and the audit verdict."""
    from .privacy.commands import self_audit_line
    from .report import format_summary, run_summary

    summary = run_summary(run_dir)
    audit = self_audit_line(run_dir)  # the run checks its own transcript
    if as_json:
        print(json.dumps({**summary, "run_dir": str(run_dir), "privacy_audit": audit}))
    else:
        print(format_summary(summary))
        print(f"run directory: {run_dir}")
        print(audit)
    return 0


def _cmd_run(a: argparse.Namespace) -> int:
    from .progress import ProgressEvents
    from .runner import start

    config = run_config(a)
    config.validate()
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = a.out or Path("runs") / f"{config.task}__{config.method}__{config.seed}__{stamp}"
    a.run_dir = out  # named by the Ctrl-C line
    if not a.quiet:
        _say(f"run directory: {out}")
    with ProgressEvents(enabled=not a.quiet, label=f"{config.task} {config.method}") as events:
        start(config, out, events.hooks())
    return _finished(out, a.json)


def _cmd_resume(a: argparse.Namespace) -> int:
    from .baselines.record import refuse_resume
    from .progress import ProgressEvents
    from .runner import Endpoint, resume

    refuse_resume(a.dir)  # an RL baseline run has no search to continue
    a.run_dir = a.dir
    endpoint = Endpoint(base_url=a.base_url, model=a.model, api_key_env=a.api_key_env)
    with ProgressEvents(enabled=not a.quiet, label=str(a.dir)) as events:
        resume(a.dir, events.hooks(), endpoint=endpoint if endpoint.given else None)
    return _finished(a.dir, a.json)


def _cmd_show(a: argparse.Namespace) -> int:
    from .report import format_summary, run_summary

    s = run_summary(a.dir)
    print(json.dumps(s) if a.json else format_summary(s))
    return 0


def _cmd_policy_eval(a: argparse.Namespace) -> int:
    from .api import evaluate_policy

    ev = evaluate_policy(a.file, episodes=a.episodes, seed=a.seed, progress=not a.quiet)
    result: dict[str, Any] = {"task": ev.task, "mean": ev.mean, "std": ev.std, "episodes": len(ev.returns), "seed": ev.seed,
                              "returns": list(ev.returns), "seeds": list(ev.seeds)}  # fmt: skip
    if a.json:
        print(json.dumps(result))
    else:
        print(f"{ev.task}: mean return {ev.mean:.2f} +- {ev.std:.2f} over {len(ev.returns)} episodes (seed {a.seed})")
    return 0


def _cmd_baseline(a: argparse.Namespace) -> int:
    from .baselines.rl import RLConfig, default_run_dir, run_baseline
    from .report import format_summary, run_summary

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
    if a.json:
        print(json.dumps(rows))
    else:
        for r in rows:
            print(f"{r['name']:<18} {r['env_id']:<20} n_s={r['n_s']:<3} n_a={r['n_a']:<3} D={r['D']:<4} {r['action_type']}")
    return 0


def _with_config_file(parser: argparse.ArgumentParser, argv: Sequence[str] | None, path: Path) -> argparse.Namespace:
    """Re-parse with the TOML file's values as the defaults of `run`, so flags on the command line win."""
    from .config import defaults_from_file

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    run = sub.choices["run"]
    run.set_defaults(**defaults_from_file(path, run._actions, skip=("config",)))
    return parser.parse_args(argv)


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
    parser = build_parser()
    try:
        return _main(parser, argv)
    except BrokenPipeError:
        return _quiet_broken_pipe()


def _main(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    args = parser.parse_args(argv)
    if getattr(args, "config", None) is not None and args.command == "run":
        try:
            args = _with_config_file(parser, argv, args.config)
        except PPPropsError as e:
            print(f"ppprops: error: {e}", file=sys.stderr)
            return EXIT_INPUT
    handlers = {"run": _cmd_run, "resume": _cmd_resume, "show": _cmd_show, "envs": _cmd_envs, "baseline": _cmd_baseline,
                "policy": _cmd_policy_eval}  # fmt: skip
    from .experiments.cli import cmd_experiment, cmd_report

    handlers.update(experiment=cmd_experiment, report=cmd_report)
    from .privacy.commands import PRIVACY_HANDLERS

    handlers.update(PRIVACY_HANDLERS)
    try:
        code = handlers[args.command](args)
        sys.stdout.flush()  # a closed pipe shows here, inside the handlers below, not at interpreter exit
        return code
    except PPPropsError as e:
        print(f"ppprops: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(interrupted_line(args), file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
