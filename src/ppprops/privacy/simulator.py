"""What an attacker who can build a task's environment simulates: episodes of decoded policies.

A provider that knows the task's public env (every Gymnasium id; a user's env only when its
task file says it is public) can run any policy on it, from any initial state the env's
``reset(seed)`` produces. The simulator attacks (``privacy.simfit``) use this to fit the secrets:
hypothesise a decoding, run the decoded shown policies, compare with the printed returns.

Two kinds of simulator, one interface (``Simulator.rollout``):

- ``VectorSim``: the public dynamics of CartPole-v1, Acrobot-v1 and Pendulum-v1, re-written in
  numpy so that thousands of hypotheses run as one array; initial states come from the real
  env's ``reset(seed)``, and the physical constants are read off the real env (so its kwargs
  count). Each reproduces ``evaluation.run_episode`` on the real env (the same float32
  observations, the same order of operations; ``tests/test_simulator.py`` compares them).
- ``EnvSim``: any other env, stepped one episode at a time through ``evaluation.run_episode``
  with the task's own recorder (exact, but thousands of times slower per episode).

Every rollout is charged to a ``Budget`` of simulated steps (one step of one episode; a
vectorised batch charges its width times its length): past it, ``OverBudget`` is raised and the
attack reports that it stopped, never hangs. The step budget does not depend on the machine or
its load, so the same transcript gives the same attack result anywhere. A wall-clock cap can be
added (``Budget.seconds``, the audit's ``--sim-seconds``); none is set by default, since a fit
cut short by the clock depends on the load.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from ..tasks.base import Task

# Env ids whose dynamics are public: every Gymnasium id is, the user's own module env is not
# (``env_is_public``, when the task's declaration does not say).
_PRIVATE_PREFIXES = ("__main__",)


class OverBudget(Exception):
    """A simulation ran past its budget (simulated steps, or the optional wall-clock cap)."""

    def __init__(self, what: str) -> None:
        super().__init__(what)
        self.what = what


@dataclass
class Budget:
    """How much an attack may simulate: ``steps`` simulated env steps in all (one step of one
    episode; a vectorised batch of N episodes of T steps costs N T), and optionally ``seconds``
    of wall clock from ``started`` (None: no cap; a cap makes the outcome depend on the machine).

    ``charge`` raises ``OverBudget`` once either is spent. ``used`` counts the steps charged.
    """

    steps: int
    seconds: float | None = None
    used: int = 0
    started: float = field(default_factory=time.monotonic)

    def charge(self, steps: int) -> None:
        """Count ``steps`` more simulated steps; raises OverBudget past the step budget or the wall-clock cap."""
        self.used += int(steps)
        if self.used > self.steps:
            raise OverBudget(f"over its budget of {self.steps:.3g} simulated steps")
        if self.seconds is not None and time.monotonic() - self.started > self.seconds:
            raise OverBudget(f"over its wall-clock cap of {self.seconds:g} s")

    def left(self) -> int:
        """Simulated steps still allowed."""
        return max(0, self.steps - self.used)


@dataclass(frozen=True)
class Outcome:
    """Raw outcomes of N episodes: ``returns`` shape (N,) in reward units, and per diagnostic the
    value each episode ended with (``diagnostics[name]``: shape (N,), float, or object for text
    diagnostics such as CartPole's ``termination``)."""

    returns: NDArray[np.float64]
    diagnostics: dict[str, NDArray[Any]]


def env_is_public(task: Task) -> bool:
    """True when an attacker can build ``task``'s env: a Gymnasium id (the paper's tasks, any id
    registered by Gymnasium or an installed package), false for a user's own module env.

    The task's declared ``public_env`` fact (its ``[privacy]`` table) when there is one. A task
    without a declaration counts as a Gymnasium id when its env id has no ``module:`` part and no
    entry point.
    """
    spec = getattr(task, "spec", None)
    declared = getattr(spec, "public_env", None) if spec is not None else None
    if callable(declared):  # TaskSpec.public_env() where task files declare it
        declared = declared()
    if isinstance(declared, bool):
        return declared
    env = getattr(spec, "env", None) if spec is not None else None
    if env is not None and getattr(env, "entry_point", None) is not None:
        ep = str(env.entry_point)
        return ep.startswith("gymnasium.")  # a registered Gymnasium id pinned to its entry point
    env_id = task.env_id
    return ":" not in env_id and not env_id.startswith(_PRIVATE_PREFIXES)


class Simulator:
    """Runs a batch of policies, each from the initial state of one ``reset`` seed.

    ``rollout(thetas, seeds)``: ``thetas`` raw parameters, shape (N, D); ``seeds`` N ints (the
    ``env.reset`` seed of each episode). Returns an ``Outcome``. Raises ``OverBudget``.
    """

    kind = "env"

    def __init__(self, task: Task, budget: Budget) -> None:
        self.task = task
        self.budget = budget

    def rollout(self, thetas: NDArray[np.float64], seeds: Sequence[int]) -> Outcome:
        """Episodes of ``thetas[i]`` from ``reset(seed=seeds[i])``; see the class docstring."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the env."""


class EnvSim(Simulator):
    """Any env: one episode at a time through ``evaluation.run_episode`` and the task's recorder."""

    kind = "env"

    def __init__(self, task: Task, budget: Budget) -> None:
        super().__init__(task, budget)
        self._env: Any = None

    def _make(self) -> Any:
        if self._env is None:
            self._env = self.task.make_env()
        return self._env

    def rollout(self, thetas: NDArray[np.float64], seeds: Sequence[int]) -> Outcome:
        """Exact episodes on the real env; charges each episode's length before the next starts."""
        from ..evaluation import make_policy, run_episode, step_cap

        env = self._make()
        cap = step_cap(env)
        rets: list[float] = []
        diags: list[dict[str, Any]] = []
        for theta, seed in zip(np.asarray(thetas, dtype=np.float64), seeds, strict=True):
            ep = run_episode(self.task, env, make_policy(self.task, theta, env), int(seed), max_steps=cap)
            self.budget.charge(int(float(ep.diagnostics.get("episode_length", 1.0))))
            rets.append(ep.ret)
            diags.append(ep.diagnostics)
        names = list(dict.fromkeys(k for d in diags for k in d))
        out: dict[str, NDArray[Any]] = {}
        for k in names:
            vals = [d.get(k) for d in diags]
            out[k] = (np.array(vals, dtype=np.float64) if all(isinstance(v, float) for v in vals)
                      else np.array([str(v) for v in vals], dtype=object))
        return Outcome(np.array(rets, dtype=np.float64), out)

    def close(self) -> None:
        """Close the env, if made."""
        if self._env is not None:
            self._env.close()
            self._env = None


class VectorSim(Simulator):
    """A classic-control env's public dynamics in numpy, many episodes at once (see the module
    docstring); subclasses give ``_init``, ``_obs`` and ``_step``."""

    kind = "vector"
    env_ids: tuple[str, ...] = ()

    def __init__(self, task: Task, budget: Budget) -> None:
        super().__init__(task, budget)
        env = task.make_env()
        try:
            self.limit = int(env.spec.max_episode_steps) if env.spec and env.spec.max_episode_steps else 10_000
            self.u = env.unwrapped
            self._reset_env = env
            self._states: dict[int, NDArray[np.float64]] = {}
            space = env.action_space
            self.low = None if task.discrete else np.asarray(space.low, dtype=np.float64)
            self.high = None if task.discrete else np.asarray(space.high, dtype=np.float64)
        except Exception:
            env.close()
            raise
        sel = task.observation
        self.indices = getattr(sel, "indices", None)

    def initial_state(self, seed: int) -> NDArray[np.float64]:
        """The state ``reset(seed=seed)`` of the real env starts from (cached)."""
        s = self._states.get(int(seed))
        if s is None:
            self._reset_env.reset(seed=int(seed))
            s = np.array(self.u.state, dtype=np.float64)
            self._states[int(seed)] = s
        return s

    def close(self) -> None:
        """Close the env used for resets."""
        self._reset_env.close()

    def _policy(self, thetas: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[Any]:
        n_s, n_a = self.task.n_s, self.task.n_a
        if self.indices is not None:
            s = s[:, list(self.indices)]
        if not self.task.policy.is_linear:
            return self._act(self._mlp(thetas, s))
        W = thetas[:, : n_s * n_a].reshape(-1, n_s, n_a)
        u = s[:, 0, None] * W[:, 0, :]
        for i in range(1, n_s):  # the order of LinearPolicy.scores (s @ W), then + b
            u = u + s[:, i, None] * W[:, i, :]
        u = u + thetas[:, n_s * n_a:]
        return self._act(u)

    def _mlp(self, thetas: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
        """The MLP's forward pass (``ppprops.policy.FORWARD_TEXT``) for N parameter vectors and states at once: u, shape (N, n_a)."""
        from ..policy import activate

        policy, n_s, n_a = self.task.policy, self.task.n_s, self.task.n_a
        shapes = policy.layer_shapes(n_s, n_a)
        h = s
        for number, ((w, b), (i, o)) in enumerate(zip(policy.layer_slices(n_s, n_a), shapes, strict=True), start=1):
            h = np.einsum("ni,nio->no", h, thetas[:, w].reshape(-1, i, o)) + thetas[:, b]
            if number < len(shapes):
                h = activate(h, policy.activation)
        return h

    def _act(self, u: NDArray[np.float64]) -> NDArray[Any]:
        if self.task.discrete:
            return np.argmax(u, axis=1)
        assert self.low is not None and self.high is not None
        return np.minimum(np.maximum(u, self.low), self.high)

    def rollout(self, thetas: NDArray[np.float64], seeds: Sequence[int]) -> Outcome:
        """All N episodes advanced together; finished ones stop accumulating and charging, and
        are dropped from the arrays once they are half of them."""
        thetas = np.asarray(thetas, dtype=np.float64)
        N = len(thetas)
        state = np.array([self.initial_state(s) for s in seeds], dtype=np.float64).reshape(N, -1)
        ret = np.zeros(N)
        steps = np.zeros(N)
        acc = self._start(N)
        idx = np.arange(N)  # the episodes in the working arrays
        th, st, ob = thetas, state, self._obs(state)
        live = np.ones(N, dtype=bool)  # of the working arrays
        r_w = np.zeros(N)
        n_live = N
        for _ in range(self.limit):
            if n_live == 0:
                break
            if n_live <= len(idx) // 2:  # compact: keep the running episodes only
                keep = np.flatnonzero(live)
                ret[idx] += r_w
                idx, th, st, ob, r_w = idx[keep], th[keep], st[keep], ob[keep], np.zeros(len(keep))
                live = np.ones(len(keep), dtype=bool)
            self.budget.charge(n_live)
            act = self._policy(th, ob)
            new, reward, term = self._step(st, act)
            st = np.where(live[:, None], new, st)
            ob = self._obs(st)
            r_w = r_w + np.where(live, reward, 0.0)
            steps[idx[live]] += 1
            ended = term & live
            self._record(acc, idx, ob, ended, live)
            live = live & ~term
            n_live = int(live.sum())
        ret[idx] += r_w
        return Outcome(ret, self._finish(acc, steps))

    # -- per-env parts ------------------------------------------------------------------------
    def _start(self, N: int) -> dict[str, NDArray[Any]]:
        return {"terminated": np.zeros(N, dtype=bool)}

    def _record(self, acc: dict[str, NDArray[Any]], idx: NDArray[np.intp], obs: NDArray[np.float64], ended: NDArray[np.bool_],
                live: NDArray[np.bool_]) -> None:
        """Per-step bookkeeping of the diagnostics: ``idx`` the episodes of the working arrays,
        ``obs`` their observations after the step, ``ended`` those that ended at it, ``live``
        those that took it."""
        acc["terminated"][idx[ended]] = True

    def _finish(self, acc: dict[str, NDArray[Any]], steps: NDArray[np.float64]) -> dict[str, NDArray[Any]]:
        return {"episode_length": steps.copy()}

    def _obs(self, state: NDArray[np.float64]) -> NDArray[np.float64]:
        raise NotImplementedError

    def _step(self, state: NDArray[np.float64], act: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        raise NotImplementedError


class PendulumSim(VectorSim):
    """Pendulum-v1: reward -(angle^2 + 0.1 thdot^2 + 0.001 u^2), never terminates (time limit only)."""

    env_ids = ("Pendulum-v1",)

    def _obs(self, state: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.empty((len(state), 3), dtype=np.float32)
        out[:, 0] = np.cos(state[:, 0])
        out[:, 1] = np.sin(state[:, 0])
        out[:, 2] = state[:, 1]
        return out.astype(np.float64)

    def _step(self, state: NDArray[np.float64], act: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        e = self.u
        th, thdot = state[:, 0], state[:, 1]
        u = np.minimum(np.maximum(act[:, 0], -e.max_torque), e.max_torque)
        norm = ((th + np.pi) % (2 * np.pi)) - np.pi
        costs = norm**2 + 0.1 * thdot**2 + 0.001 * (u**2)
        newthdot = thdot + (3 * e.g / (2 * e.l) * np.sin(th) + 3.0 / (e.m * e.l**2) * u) * e.dt
        newthdot = np.minimum(np.maximum(newthdot, -e.max_speed), e.max_speed)
        new = np.empty_like(state)
        new[:, 0] = th + newthdot * e.dt
        new[:, 1] = newthdot
        return new, -costs, np.zeros(len(th), dtype=bool)


class CartPoleSim(VectorSim):
    """CartPole-v1 (Euler integration): +1 per step; the diagnostics of ``tasks.classic.CartPoleRecorder``."""

    env_ids = ("CartPole-v1",)

    def _obs(self, state: NDArray[np.float64]) -> NDArray[np.float64]:
        return state.astype(np.float32).astype(np.float64)

    def _step(self, state: NDArray[np.float64], act: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        e = self.u
        if getattr(e, "kinematics_integrator", "euler") != "euler" or getattr(e, "_sutton_barto_reward", False):
            raise OverBudget("a CartPole variant this simulator does not model")
        x, x_dot, theta, theta_dot = state.T
        force = np.where(act == 1, e.force_mag, -e.force_mag)
        costheta, sintheta = np.cos(theta), np.sin(theta)
        temp = (force + e.polemass_length * np.square(theta_dot) * sintheta) / e.total_mass
        thetaacc = (e.gravity * sintheta - costheta * temp) / (e.length * (4.0 / 3.0 - e.masspole * np.square(costheta) / e.total_mass))
        xacc = temp - e.polemass_length * thetaacc * costheta / e.total_mass
        x = x + e.tau * x_dot
        x_dot = x_dot + e.tau * xacc
        theta = theta + e.tau * theta_dot
        theta_dot = theta_dot + e.tau * thetaacc
        term = (x < -e.x_threshold) | (x > e.x_threshold) | (theta < -e.theta_threshold_radians) | (theta > e.theta_threshold_radians)
        return np.stack([x, x_dot, theta, theta_dot], axis=1), np.ones(len(x)), term

    def _start(self, N: int) -> dict[str, NDArray[Any]]:
        return {"terminated": np.zeros(N, dtype=bool), "out": np.zeros(N, dtype=bool)}

    def _record(self, acc: dict[str, NDArray[Any]], idx: NDArray[np.intp], obs: NDArray[np.float64], ended: NDArray[np.bool_],
                live: NDArray[np.bool_]) -> None:
        acc["terminated"][idx[ended]] = True
        acc["out"][idx[ended]] = np.abs(obs[ended, 0]) > 2.4

    def _finish(self, acc: dict[str, NDArray[Any]], steps: NDArray[np.float64]) -> dict[str, NDArray[Any]]:
        cause = np.where(acc["terminated"], np.where(acc["out"], "cart_out_of_bounds", "pole_fell"),
                         np.where(steps >= self.limit, "time_limit", "stopped")).astype(object)
        return {"episode_length": steps.copy(), "termination": cause}


class AcrobotSim(VectorSim):
    """Acrobot-v1 (RK4, "book" dynamics): -1 per step until the tip is above the line; the
    diagnostics of ``tasks.classic.AcrobotRecorder`` (success, mean tip height)."""

    env_ids = ("Acrobot-v1",)

    def _obs(self, state: NDArray[np.float64]) -> NDArray[np.float64]:
        t1, t2 = state[:, 0], state[:, 1]
        return np.stack([np.cos(t1), np.sin(t1), np.cos(t2), np.sin(t2), state[:, 2], state[:, 3]],
                        axis=1).astype(np.float32).astype(np.float64)

    def _dsdt(self, s: NDArray[np.float64], a: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        e = self.u
        m1, m2, l1 = e.LINK_MASS_1, e.LINK_MASS_2, e.LINK_LENGTH_1
        lc1, lc2, I1, I2, g = e.LINK_COM_POS_1, e.LINK_COM_POS_2, e.LINK_MOI, e.LINK_MOI, 9.8
        theta1, theta2, dtheta1, dtheta2 = s[:, 0], s[:, 1], s[:, 2], s[:, 3]
        d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * np.cos(theta2)) + I1 + I2
        d2 = m2 * (lc2**2 + l1 * lc2 * np.cos(theta2)) + I2
        phi2 = m2 * lc2 * g * np.cos(theta1 + theta2 - math.pi / 2.0)
        phi1 = (-m2 * l1 * lc2 * dtheta2**2 * np.sin(theta2) - 2 * m2 * l1 * lc2 * dtheta2 * dtheta1 * np.sin(theta2)
                + (m1 * lc1 + m2 * l1) * g * np.cos(theta1 - math.pi / 2) + phi2)
        if e.book_or_nips == "nips":
            ddtheta2 = (a + d2 / d1 * phi1 - phi2) / (m2 * lc2**2 + I2 - d2**2 / d1)
        else:
            ddtheta2 = (a + d2 / d1 * phi1 - m2 * l1 * lc2 * dtheta1**2 * np.sin(theta2) - phi2) / (m2 * lc2**2 + I2 - d2**2 / d1)
        ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
        return dtheta1, dtheta2, ddtheta1, ddtheta2

    def _step(self, state: NDArray[np.float64], act: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        e = self.u
        if getattr(e, "torque_noise_max", 0) > 0:
            raise OverBudget("an Acrobot variant with torque noise, which this simulator does not model")
        torque = np.asarray(e.AVAIL_TORQUE, dtype=np.float64)[act]
        dt = e.dt
        dt2 = dt / 2.0
        y0 = state
        k1 = np.stack(self._dsdt(y0, torque), axis=1)
        k2 = np.stack(self._dsdt(y0 + dt2 * k1, torque), axis=1)
        k3 = np.stack(self._dsdt(y0 + dt2 * k2, torque), axis=1)
        k4 = np.stack(self._dsdt(y0 + dt * k3, torque), axis=1)
        ns = y0 + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        for j in (0, 1):
            col = ns[:, j]
            while np.any(col > math.pi):
                col = np.where(col > math.pi, col - 2 * math.pi, col)
            while np.any(col < -math.pi):
                col = np.where(col < -math.pi, col + 2 * math.pi, col)
            ns[:, j] = col
        ns[:, 2] = np.minimum(np.maximum(ns[:, 2], -e.MAX_VEL_1), e.MAX_VEL_1)
        ns[:, 3] = np.minimum(np.maximum(ns[:, 3], -e.MAX_VEL_2), e.MAX_VEL_2)
        term = -np.cos(ns[:, 0]) - np.cos(ns[:, 1] + ns[:, 0]) > 1.0
        return ns, np.where(term, 0.0, -1.0), term

    def _start(self, N: int) -> dict[str, NDArray[Any]]:
        return {"terminated": np.zeros(N, dtype=bool), "height": np.zeros(N)}

    def _record(self, acc: dict[str, NDArray[Any]], idx: NDArray[np.intp], obs: NDArray[np.float64], ended: NDArray[np.bool_],
                live: NDArray[np.bool_]) -> None:
        acc["terminated"][idx[ended]] = True
        c1, s1, c2, s2 = obs[live, 0], obs[live, 1], obs[live, 2], obs[live, 3]
        acc["height"][idx[live]] = acc["height"][idx[live]] + (-c1 - (c1 * c2 - s1 * s2))

    def _finish(self, acc: dict[str, NDArray[Any]], steps: NDArray[np.float64]) -> dict[str, NDArray[Any]]:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_h = np.where(steps > 0, acc["height"] / np.maximum(steps, 1), 0.0)
        return {"episode_length": steps.copy(), "success": acc["terminated"].astype(np.float64), "mean_tip_height": mean_h}


VECTOR_SIMS: tuple[type[VectorSim], ...] = (PendulumSim, CartPoleSim, AcrobotSim)


def simulator_for(task: Task, budget: Budget) -> tuple[Simulator | None, str]:
    """The simulator an attacker can build for ``task`` (None with the reason when it cannot).

    A vectorised one for the classic-control ids above when the task feeds the policy the env's
    plain observation (or a selection of its values), else one that steps the real env. Making
    the env may fail (a missing simulator extra): then None and why.
    """
    if not env_is_public(task):
        return None, f"the env of task {task.name} is private (its dynamics cannot be simulated by the provider)"
    sel = task.observation
    plain = getattr(sel, "keys", None) is None and getattr(sel, "one_hot", None) is None
    base_id = task.env_id.split(":")[-1]
    try:
        for cls in VECTOR_SIMS:
            if base_id in cls.env_ids and plain:
                return cls(task, budget), ""
        return EnvSim(task, budget), ""
    except Exception as e:  # the env cannot be made here (a missing extra): the attack cannot run
        return None, f"its env cannot be made here ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
