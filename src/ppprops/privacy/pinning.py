"""How many shown candidates a simulator fit needs to pin a run's secrets (docs/threat-model.md).

For each task, scheme and seed, one offline run (the stand-in optimizer, ``privacy.simulate``);
then the provider's view after each prefix of its requests, i.e. after N distinct shown entries,
is attacked with ``sim-exact`` (initial states known) and ``sim-marginal`` (unknown), and the
estimates are scored against the key file. A secret counts as pinned within 1%.

    python -m ppprops.privacy.pinning --envs CartPole,Acrobot,Pendulum-v1,InvertedPendulum-v5 \\
        --seeds 3 --shown 5,10,20 --out runs/pinning

Writes ``pinning.md`` (the table) and ``pinning.json`` (every fit) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .requests import load_requests
from .simfit import DEFAULT_LIMITS, SimLimits, fit_view
from .view import view_of

PINNED = 0.01


def _err(est: float | np.ndarray, true: float | np.ndarray) -> Any:
    return np.expm1(np.abs(np.log(np.asarray(est, dtype=np.float64) / true)))


def measure(out: Path, envs: Sequence[str], seeds: int, shown: Sequence[int], warmup: int, iterations: int,
            limits: SimLimits, log: Any = print) -> list[dict[str, Any]]:
    """Every (task, scheme, seed, N, mode) fit, scored: a list of JSON rows."""
    from ..rundir import open_run
    from .audit import search_config
    from .matrix import run_matrix

    dirs = run_matrix(out, envs=envs, seeds=range(seeds), warmup=warmup, iterations=iterations, final_episodes=0,
                      log=log, offline=True)
    rows = []
    for d in dirs:
        with open_run(d) as run:
            config = search_config(run.stored, d)
            task = run.task
            secrets = run.load_secrets()
            cands = run.store.candidates()
        requests = load_requests(d)
        for n in shown:
            k = next((k for k in range(1, len(requests) + 1) if len(view_of(requests[:k], task, config.box).entries) >= n), None)
            if k is None:
                continue
            for mode in ("exact", "marginal"):
                v = view_of(requests[:k], task, config.box)
                v.memo["sim_limits"] = limits
                t0 = time.time()
                fit = fit_view(v, mode)
                row: dict[str, Any] = {"task": task.name, "scheme": config.method, "seed": config.seed, "target": n,
                                       "shown": len(v.entries), "mode": mode, "seconds": round(time.time() - t0, 1)}
                if isinstance(fit, str):
                    row["not_run"] = fit
                else:
                    row["c"] = float(_err(fit.c, secrets.c))
                    row["a"] = float(np.median(_err(fit.a, secrets.a)))
                    best = int(np.argmax([v.entries[p].ret for p in fit.entries]))
                    e = v.entries[fit.entries[best]]
                    cand = min(cands, key=lambda c: float(np.max(np.abs(np.asarray(c.params_enc) - e.params))))
                    row["raw"] = float(abs(fit.raw_returns[best] - cand.ret) / abs(cand.ret)) if cand.ret else math.nan
                    row["prior_c"] = float(_err(1.0, secrets.c))
                    row["prior_a"] = float(np.median(_err(1.0, secrets.a)))
                    row["steps"] = fit.steps
                rows.append(row)
                log(f"{d.name} N={row['shown']} {mode}: " + (row.get("not_run") or
                    f"c {100 * row['c']:.3g}% a {100 * row['a']:.3g}% raw {100 * row['raw']:.3g}% ({row['seconds']} s)"))
    return rows


def table(rows: Sequence[dict[str, Any]], shown: Sequence[int]) -> str:
    """Markdown: per task, scheme and initial-state knowledge, for each N: runs pinned (c, a, raw
    return within 1%) and the median errors."""
    keys = sorted({(r["task"], r["scheme"], r["mode"]) for r in rows})
    head = "| task | scheme | initial states | " + " | ".join(f"N = {n}" for n in shown) + " |"
    lines = [head, "|" + "---|" * (3 + len(shown))]
    for task, scheme, mode in keys:
        cells = []
        for n in shown:
            rs = [r for r in rows if (r["task"], r["scheme"], r["mode"], r["target"]) == (task, scheme, mode, n)]
            ran = [r for r in rs if "not_run" not in r]
            if not rs:
                cells.append("-")
            elif not ran:
                cells.append("not run")
            else:
                pinned = {k: f"{sum(r[k] <= PINNED for r in ran)}/{len(ran)}" for k in ("c", "a", "raw")}
                med = {k: float(np.median([r[k] for r in ran])) for k in ("c", "a", "raw")}
                cells.append(f"c {pinned['c']} ({100 * med['c']:.2g}%), a {pinned['a']} ({100 * med['a']:.2g}%), "
                             f"raw {pinned['raw']} ({100 * med['raw']:.2g}%)")
        lines.append(f"| {task} | {scheme} | {'known' if mode == 'exact' else 'unknown'} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m ppprops.privacy.pinning``: run the measurement, print and write the table."""
    p = argparse.ArgumentParser(prog="python -m ppprops.privacy.pinning", description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", default="CartPole,Acrobot,Pendulum-v1,InvertedPendulum-v5")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--shown", default="5,10,20", help="numbers of shown entries at which to attack")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--iterations", type=int, default=20)
    p.add_argument("--sim-steps", type=int, default=DEFAULT_LIMITS.vector_steps)
    p.add_argument("--out", type=Path, default=Path("runs") / "pinning")
    a = p.parse_args(argv)
    shown = [int(x) for x in a.shown.split(",")]
    ratio = DEFAULT_LIMITS.vector_steps // DEFAULT_LIMITS.env_steps
    limits = SimLimits(vector_steps=a.sim_steps, env_steps=max(1, a.sim_steps // ratio))
    envs = [e.strip() for e in a.envs.split(",") if e.strip()]
    rows = measure(a.out, envs, a.seeds, shown, a.warmup, a.iterations, limits, log=lambda s: print(s, file=sys.stderr))
    text = table(rows, shown)
    a.out.mkdir(parents=True, exist_ok=True)
    command = "python -m ppprops.privacy.pinning " + " ".join(shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
    (a.out / "pinning.md").write_text(f"Produced by: `{command}`\n\n{text}\n", encoding="utf-8")
    (a.out / "pinning.json").write_text(json.dumps(rows, indent=1), encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
