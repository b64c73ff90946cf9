"""The `ppprops` command. It alone turns PPPropsError into one line on stderr and exit code 2."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from . import __version__
from .config import LLMConfig, RunConfig
from .errors import PPPropsError
from .methods import PRESETS, Mechanisms, resolve
from .strategies import BLACK_BOX

EXIT_INPUT = 2


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse's default prints usage too)
        self.exit(EXIT_INPUT, f"ppprops: error: {message}\n")


def _box(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH, got {text!r}") from None
    return lo, hi


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
    r.add_argument("--env", required=True, help="task name (see `ppprops envs`) or its Gymnasium id")
    r.add_argument("--method", choices=[*PRESETS, *BLACK_BOX], default="pp",
                   help="a preset of the paper (default pp), or a black-box baseline at the same budget")
    r.add_argument("--warmup", type=int, default=10, help="random warm-up policies (default 10)")
    r.add_argument("--iterations", type=int, default=50, help="LLM iterations (default 50)")
    r.add_argument("--top-k", type=int, default=10, help="history entries in the prompt; 0 = all (default 10)")
    r.add_argument("--episodes", type=int, default=1, help="episodes per candidate (default 1)")
    r.add_argument("--final-episodes", type=int, default=20, help="fresh episodes for the best policy (default 20)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", type=Path, default=None, help="run directory (default runs/<task>__<method>__<seed>__<time>)")
    r.add_argument("--box", type=_box, default=(-6.0, 6.0), metavar="LOW,HIGH", help="feasible range of every parameter")
    r.add_argument("--decimals", type=int, default=2, help="decimals of numbers in the prompt (default 2)")
    r.add_argument("--parse-retries", type=int, default=2, help="corrections asked for before a fallback (default 2)")
    g = r.add_argument_group("mechanisms (override the preset one by one)")
    for name in ("encode-params", "scale-rewards", "detailed-feedback", "disclose-optimum", "disclose-reward-structure"):
        g.add_argument(f"--{name}", type=_flag, default=None, metavar="on|off")
    llm = r.add_argument_group("LLM endpoint (default: the embedded Gemma 3 270M, offline)")
    llm.add_argument("--base-url", default=None, help="OpenAI-compatible endpoint, e.g. http://localhost:11434/v1")
    llm.add_argument("--model", default=None)
    llm.add_argument("--api-key-env", default=None, metavar="VAR", help="environment variable that holds the API key")
    llm.add_argument("--temperature", type=float, default=1.0)
    llm.add_argument("--max-tokens", type=int, default=None)
    llm.add_argument("--timeout", type=float, default=300.0, help="seconds per request (default 300)")
    llm.add_argument("--reasoning-effort", default=None, choices=["minimal", "low", "medium", "high"])
    llm.add_argument("--structured", default="auto", choices=["auto", "json_schema", "grammar", "none"],
                     help="constrained output: auto = grammar for the embedded model, JSON schema otherwise")
    llm.add_argument("--context-size", type=int, default=16384, help="embedded model context (default 16384)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")

    rs = sub.add_parser("resume", help="continue an interrupted run with its own secrets")
    rs.add_argument("dir", type=Path)
    rs.add_argument("--quiet", action="store_true")

    sh = sub.add_parser("show", help="summarise a run")
    sh.add_argument("dir", type=Path)
    sh.add_argument("--json", action="store_true", help="one JSON object with every candidate and LLM call")

    pol = sub.add_parser("policy", help="work with a policy file")
    polsub = pol.add_subparsers(dest="policy_command", required=True, parser_class=_Parser)
    pe = polsub.add_parser("eval", help="run a best_policy.json with no encoding involved")
    pe.add_argument("file", type=Path)
    pe.add_argument("--episodes", type=int, default=20)
    pe.add_argument("--seed", type=int, default=0)
    pe.add_argument("--json", action="store_true")

    en = sub.add_parser("envs", help="list the tasks")
    en.add_argument("--json", action="store_true")
    return p


def _run_config(a: argparse.Namespace) -> RunConfig:
    if a.method in BLACK_BOX:
        # no prompt: only whether the optimizer works in the encoded space matters
        mech = Mechanisms(bool(a.encode_params), bool(a.encode_params), False, False, False)
    else:
        mech = resolve(
            a.method,
            encode_params=a.encode_params,
            scale_rewards=a.scale_rewards,
            detailed_feedback=a.detailed_feedback,
            disclose_optimum=a.disclose_optimum,
            disclose_reward_structure=a.disclose_reward_structure,
        )
    from .tasks import get_task

    task = get_task(a.env)
    return RunConfig(
        task=task.name,
        method=a.method,
        mechanisms=mech,
        warmup=a.warmup,
        iterations=a.iterations,
        top_k=a.top_k,
        episodes=a.episodes,
        final_episodes=a.final_episodes,
        seed=a.seed,
        box=a.box,
        decimals=a.decimals,
        parse_retries=a.parse_retries,
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
        ),
    )


def _cmd_run(a: argparse.Namespace) -> int:
    from .progress import ProgressEvents
    from .report import format_summary, run_summary
    from .runner import start

    config = _run_config(a)
    config.validate()
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = a.out or Path("runs") / f"{config.task}__{config.method}__{config.seed}__{stamp}"
    with ProgressEvents(enabled=not a.quiet, label=f"{config.task} {config.method}") as events:
        start(config, out, events.hooks())
    print(format_summary(run_summary(out)))
    print(f"run directory: {out}")
    return 0


def _cmd_resume(a: argparse.Namespace) -> int:
    from .progress import ProgressEvents
    from .report import format_summary, run_summary
    from .runner import resume

    with ProgressEvents(enabled=not a.quiet, label=str(a.dir)) as events:
        resume(a.dir, events.hooks())
    print(format_summary(run_summary(a.dir)))
    return 0


def _cmd_show(a: argparse.Namespace) -> int:
    from .report import format_summary, run_summary

    s = run_summary(a.dir)
    print(json.dumps(s) if a.json else format_summary(s))
    return 0


def _cmd_policy_eval(a: argparse.Namespace) -> int:
    import numpy as np

    from . import seeding
    from .errors import ConfigError
    from .evaluation import Evaluator
    from .policy_file import read_policy
    from .tasks import get_task

    if a.episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {a.episodes}")
    doc, theta = read_policy(a.file)
    task = get_task(str(doc.get("task")))
    if (task.n_s, task.n_a) != (int(doc["n_s"]), int(doc["n_a"])):
        raise ConfigError(f"policy file {a.file} has n_s={doc['n_s']}, n_a={doc['n_a']}; task {task.name} needs {task.n_s}, {task.n_a}")
    seeds = seeding.final_eval_seeds(a.seed, a.episodes)
    with Evaluator(task) as ev:
        returns = list(ev.evaluate(theta, seeds).episode_returns)
    result: dict[str, Any] = {"task": task.name, "mean": float(np.mean(returns)), "std": float(np.std(returns)),
                              "episodes": len(returns), "seed": a.seed, "returns": returns}
    if a.json:
        print(json.dumps(result))
    else:
        print(f"{task.name}: mean return {result['mean']:.2f} +- {result['std']:.2f} over {len(returns)} episodes (seed {a.seed})")
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


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handlers = {"run": _cmd_run, "resume": _cmd_resume, "show": _cmd_show, "envs": _cmd_envs}
    try:
        if args.command == "policy":
            return _cmd_policy_eval(args)
        return handlers[args.command](args)
    except PPPropsError as e:
        print(f"ppprops: error: {e}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("ppprops: interrupted; continue with 'ppprops resume DIR'", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
