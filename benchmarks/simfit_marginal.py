"""How well the marginal simulator fit recovers the reward scale c, and how well any fit could.

Makes (or reuses) offline runs of one task and preset (the ``privacy-report --offline`` stand-in:
warm-up 10, 10 iterations answered by ``privacy.simulate.EchoOptimizer``), each with secrets drawn
by the product's own routine (``Secrets.generate`` / ``generate_hardened``) from a generator
seeded per run, and prints per run and in median the relative error of c
(``privacy.matrix._rel``: exp|ln(est/true)| - 1) for:

- ``sim-marginal`` and ``sim-marginal-lattice``: the product's marginal fit on the run's
  transcript (a and m searched, within the audit's step budget, which makes results repeat on
  a loaded machine), its c by the closed form and by the lattice posterior;
- ``bound`` (``--bound``): an attacker handed the TRUE raw parameters of every shown entry, so
  that only the reward map is left to fit from the printed returns. Each shown policy is
  simulated on ``--episodes`` public initial states; c is then estimated by the closed form of
  the product (``simfit.fit_rewards``: least squares on the simulated means), and, for integer
  returns under the warped and dithered map, by the exact likelihood of each printed return
  (``simfit.lattice_posterior``, the reading of ``sim-marginal-lattice``: the posterior median
  of c over a (p, s, c) grid with the public prior). This bounds what the returns can give: a fit
  that must also find a and m does no better.
- ``prior``: the guess c = 1.

``--returns`` also prints, per run and in mean, the mean absolute error (raw reward units) of the
raw returns of the shown entries the fit used: ``sim-marginal`` its expected return of each
decoded policy; ``sim-marginal-lattice`` each printed return read back through the lattice
reading's map (x = w_p^-1(y / c + w_p(s)), to the nearest lattice point); ``constant`` every
entry guessed as the mean of the entries' true raw returns (what a guess that knew only their
level would miss by); and, as a share of the runs, whether the best shown entry's raw return was
read within 1% (the audit's rule).

    PYTHONPATH=src nice -n 10 python benchmarks/simfit_marginal.py --task CartPole --seeds 0-21 --bound \\
        --out /tmp/simfit-bound
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import numpy as np

from ppprops.client.hardening import reward_scale
from ppprops.client.secrets import Secrets
from ppprops.privacy import simfit
from ppprops.privacy.matrix import PRIOR, _rel
from ppprops.privacy.requests import load_requests
from ppprops.privacy.simulator import Budget, simulator_for
from ppprops.privacy.view import view_of
from ppprops.tasks import Task, get_task

BOX = (-6.0, 6.0)


def secrets_for(method: str, task: Task, seed: int) -> Secrets:
    """The preset's secrets, drawn by the product's routine from a generator seeded by ``seed``."""
    rng = np.random.default_rng(9000 + seed)
    rid = f"{task.name}-{method}-{seed}"
    if method == "pp":
        return Secrets.generate(rid, task.D, rng=rng)
    return Secrets.generate_hardened(rid, task.D, box=BOX, reward_scale=reward_scale(task), rng=rng)


def make_run(out: Path, task: Task, method: str, seed: int) -> Path:
    """An offline run (EchoOptimizer answers), made once and reused."""
    from ppprops.privacy.simulate import EchoOptimizer
    from ppprops.rundir import policy_path
    from ppprops.runner import start
    from ppprops.settings import build_config

    d = out / f"{task.name}__{method}__{seed}"
    if policy_path(d).exists():
        return d
    cfg = build_config({"method": method, "warmup": 10, "iterations": 10, "final_episodes": 0, "seed": seed}, task=task)
    start(cfg, d, llm=EchoOptimizer(cfg.llm), secrets=secrets_for(method, task, seed))
    return d


def bound(run: Path, task: Task, method: str, secrets: Secrets, episodes: int) -> dict[str, float]:
    """c from the printed returns with the true raw parameters of every shown entry (module docstring)."""
    from ppprops.store import open_store

    v = view_of(load_requests(run), task, BOX)
    with open_store(run) as st:
        cands = [c for c in st.candidates() if c.source != "reeval"]
    enc = np.array([c.params_enc for c in cands])
    rows = []
    for e in v.entries:  # each shown entry's candidate, by its encoded parameters as printed
        near = np.all(np.abs(enc - np.asarray(e.params)) <= np.asarray(e.tols) * (1 + 1e-9) + 1e-12, axis=1)
        if near.any():
            rows.append((cands[int(np.argmax(near))].params, e.ret))
    theta = np.array([r[0] for r in rows])
    y = np.array([r[1] for r in rows])
    sim, why = simulator_for(task, Budget(10**12))
    if sim is None:
        raise SystemExit(why)
    draws = np.random.default_rng(simfit.MARGINAL_SEED).integers(0, 2**31, size=episodes)
    R = sim.rollout(np.repeat(theta, episodes, axis=0), np.tile(draws, len(y)).tolist()).returns.reshape(len(y), episodes)
    sim.close()
    schemes = simfit.schemes_of(v)  # the document form names no encoding: the preset's own
    scheme = schemes[0] if method == "pp" else schemes[-1]
    fit = simfit.fit_rewards(R[None], y, scheme, simfit.RewardPrior(S=reward_scale(task)), refine=40)
    out = {"closed form": _rel(float(fit.c[0]), secrets.c)}
    step = (v.facts.resolution or {}).get("return", 0.0)
    if scheme.rewards == "warp" and step > 0:  # the reading of sim-marginal-lattice, on the true policies
        c_med = simfit.lattice_posterior(R, y, step, simfit.RewardPrior(S=reward_scale(task)))[0]
        out["exact, posterior median"] = _rel(c_med, secrets.c)
    return out


def return_errors(run: Path, v: object, fit: simfit.Fit) -> dict[str, float]:
    """Mean absolute error of the raw returns of the entries the fit used (module docstring); the
    lattice reading's raw returns are the audit's own (``sim-marginal-lattice``'s raw guesses)."""
    from ppprops.privacy.exposure import shown_candidate
    from ppprops.store import open_store

    with open_store(run) as st:
        cands = st.candidates()
    guesses = simfit._raw_guesses(v, fit)  # type: ignore[arg-type]
    truth = np.array([getattr(shown_candidate(g, cands), "ret", math.nan) for g in guesses])
    best = int(np.argmax([g.ret for g in guesses]))  # the best shown entry (the warp is increasing): the one the audit scores
    readings = {"sim-marginal": np.array([g.raw_ret for g in guesses])}
    if fit.lattice is not None:
        readings["sim-marginal-lattice"] = np.array([g.raw_ret for g in simfit._lattice_guesses(v, fit)])  # type: ignore[arg-type]
    out = {"constant": float(np.nanmean(np.abs(np.nanmean(truth) - truth)))}
    out.update({k: float(np.nanmean(np.abs(x - truth))) for k, x in readings.items()})
    out.update({f"best within 1%, {k}": float(abs(x[best] - truth[best]) <= 0.01 * abs(truth[best])) for k, x in readings.items()})
    return out


def seeds_of(text: str) -> list[int]:
    """'0-3,7' -> [0, 1, 2, 3, 7]."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CartPole")
    ap.add_argument("--method", default="pp-hardened", choices=["pp", "pp-hardened"])
    ap.add_argument("--seeds", default="0-10")
    ap.add_argument("--out", type=Path, default=Path("/tmp/simfit-runs"))
    ap.add_argument("--steps", type=float, default=simfit.DEFAULT_LIMITS.vector_steps, help="the fit's step bound")
    ap.add_argument("--no-fit", action="store_true", help="skip the product's fit (with --bound: the bound alone)")
    ap.add_argument("--bound", action="store_true", help="also the true-parameter bound")
    ap.add_argument("--episodes", type=int, default=64, help="simulated episodes per shown policy in the bound")
    ap.add_argument("--returns", action="store_true", help="also the error of the raw returns the fit reads")
    a = ap.parse_args()
    task = get_task(a.task)
    errors: dict[str, list[float]] = {}
    ret_errors: dict[str, list[float]] = {}
    for seed in seeds_of(a.seeds):
        run = make_run(a.out, task, a.method, seed)
        s = secrets_for(a.method, task, seed)
        row = {"prior": float(_rel(PRIOR, s.c))}
        note = ""
        if not a.no_fit:
            v = view_of(load_requests(run), task, BOX)
            v.memo["sim_limits"] = simfit.SimLimits(vector_steps=int(a.steps))
            t0 = time.process_time()
            fit = simfit.fit_view(v, "marginal")
            row["sim-marginal"] = float(_rel(fit.c if not isinstance(fit, str) else PRIOR, s.c))
            if not isinstance(fit, str) and fit.lattice is not None:
                row["sim-marginal-lattice"] = float(_rel(fit.lattice[0], s.c))
            note = f" ({time.process_time() - t0:.0f} s CPU{'; ' + fit if isinstance(fit, str) else ''})"
            if a.returns and not isinstance(fit, str):
                got = return_errors(run, v, fit)
                for k, e in got.items():
                    ret_errors.setdefault(k, []).append(e)
                note += "  raw returns: " + "  ".join(f"{k} {e:.1f}" for k, e in got.items())
        if a.bound:
            row.update(bound(run, task, a.method, s, a.episodes))
        for k, e in row.items():
            errors.setdefault(k, []).append(e)
        print(f"seed {seed}: c {s.c:.4g}  " + "  ".join(f"{k} {100 * e:.1f}%" for k, e in row.items()) + note, flush=True)
    print(f"{a.task} {a.method}, {len(errors['prior'])} runs, median error of c: "
          + ", ".join(f"{k} {100 * statistics.median(e):.1f}%" for k, e in errors.items()))
    if ret_errors:
        print("raw returns of the shown entries, mean absolute error, mean over runs (median): "
              + ", ".join(f"{k} {statistics.mean(e):.1f} ({statistics.median(e):.1f})" for k, e in ret_errors.items()
                          if not k.startswith("best"))
              + "; best shown entry's raw return within 1%: "
              + ", ".join(f"{k.split(', ')[1]} {int(sum(e))}/{len(e)}" for k, e in ret_errors.items() if k.startswith("best")))


if __name__ == "__main__":
    main()
