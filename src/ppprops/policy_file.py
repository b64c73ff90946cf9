"""The deployable result: ``best_policy.json``, a linear policy with no encoding involved.

Format ``ppprops.linear_policy/2`` holds everything needed to run the policy with numpy and
gymnasium alone (the README's recipe)::

    {
      "format": "ppprops.linear_policy/2",
      "task": "Ant-Ultra", "env_id": "Ant-v5",
      "env": {"spec": {...},                  # Gymnasium's EnvSpec as JSON: gym.make(EnvSpec.from_json(...))
              "imports": [...], "paths": [...]},  # modules to import / folders to put on sys.path first
      "observation": {"names": [...],         # names of s[0..n_s-1]
                      "keys": null,           # Dict observation: entries kept, in this order (flattened, concatenated)
                      "one_hot": null,        # Discrete observation: {"n": N, "start": S} -> one-hot vector of length N
                      "indices": [0, 5, ...]},  # values kept of the flattened float64 vector
      "action": {"type": "continuous", "rule": "clip", "low": [...], "high": [...]}
             or {"type": "discrete", "rule": "argmax", "n": 5},
      "n_s": 10, "n_a": 8, "action_type": "continuous",
      "W": [[...n_a values...], ... n_s rows],  # u = W^T s + b, i.e. u = s @ W + b
      "b": [...n_a values...],
      "theta": [...D values...],                # the same numbers in the flat layout
      "versions": {"ppprops": ..., "gymnasium": ..., "numpy": ..., "python": ..., <simulator>: ...},
      "task_spec": {...},                       # the task's declaration (ppprops rebuilds the task from it)
      "search": {"run_id": ..., "method": ..., "seed": ..., "return": ..., "candidate": ...},
      "final_eval": {"mean": ..., "std": ..., "episodes": ..., "seed": ...}
    }

An action bound that is infinite is written as the largest float, so the file stays strict JSON
and clipping to it changes no finite value. A task without env (a robot outside Python, driven
with ask/tell) writes ``"env": null`` and ``"env_id": null``, and its declared bounds
(``action_low`` / ``action_high`` of its task file) as the clip rule's bounds: the file holds the
policy alone, which the user's own code applies to the robot's observations. ``load_policy`` reads either format version
(``/1`` files, which name only the task, are completed from ppprops' task registry).

An MLP policy (``ppprops.policy.PolicySpec``) is written as format ``ppprops.mlp_policy/1``: the
same blocks, with the network instead of ``W`` and ``b``::

      "policy": {"kind": "mlp", "hidden": [16], "activation": "tanh"},
      "forward": "h_0 = s; h_l = act(h_{l-1} @ W_l + b_l) ...",   # the forward pass, in words (FORWARD_TEXT)
      "layers": [{"W": [...fan_in rows of fan_out values...], "b": [...fan_out values...]}, ...],  # input to output
      "theta": [...D values...],                # the same numbers: each layer's W (row-major), then its b
"""

from __future__ import annotations

import importlib
import json
import os
import platform
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import ConfigError, PPPropsError
from .policy import FORWARD_TEXT, LINEAR, LinearPolicy, MLPPolicy, PolicySpec, make_network, param_count, parse_policy
from .tasks.base import Selection, Task

FORMAT = "ppprops.linear_policy/2"
FORMAT_V1 = "ppprops.linear_policy/1"
FORMAT_MLP = "ppprops.mlp_policy/1"
FORMATS = (FORMAT, FORMAT_V1, FORMAT_MLP)
_BIG = float(np.finfo(np.float64).max)


def _bound(values: Any, n: int) -> list[float]:
    arr = np.broadcast_to(np.asarray(values, dtype=np.float64), (n,))
    return [float(np.clip(v, -_BIG, _BIG)) for v in arr]


def _versions(entry_point: str | None) -> dict[str, str]:
    import importlib.metadata as md

    import gymnasium

    from .version import __version__

    out = {"ppprops": __version__, "gymnasium": gymnasium.__version__, "numpy": np.__version__, "python": platform.python_version()}
    modules = {"mujoco"} | ({entry_point.split(":")[0].split(".")[0]} if entry_point else set())
    dists = md.packages_distributions()
    for module in sorted(modules):
        if module in sys.modules:
            for dist in dists.get(module, ()):
                try:
                    out[dist] = md.version(dist)
                except md.PackageNotFoundError:
                    pass
    return out


def env_document(task: Task) -> dict[str, Any] | None:
    """How to make the task's env: Gymnasium's EnvSpec (JSON), plus modules to import and folders for sys.path.

    None for a task without env (``Task.has_env`` False).
    """
    from .tasks.envs import EnvRecipe

    if not task.has_env:
        return None
    recipe = task.spec.env if task.spec is not None else EnvRecipe(id=task.env_id, kwargs=dict(task.env_kwargs))
    spec = recipe.env_spec()
    try:
        spec_json = json.loads(spec.to_json())
    except (ValueError, TypeError):  # an entry point with no importable name: this process only
        spec_json = None
    return {"spec": spec_json, "imports": list(recipe.imports), "paths": list(recipe.paths)}


def policy_document(
    task: Task, theta: np.ndarray, *, env: Any, search: dict[str, Any], final_eval: dict[str, Any] | None
) -> dict[str, Any]:
    """The policy file's content for ``theta`` (shape (D,)) on ``task``.

    Continuous actions are clipped to the bounds of ``env``'s action space; ``env`` None takes the
    task's declared bounds (a task without env) or, failing those, makes the env to read them
    (``Task.action_bounds``). Discrete actions need no env.
    """
    pol = make_network(theta, task.policy, task.n_s, task.n_a, discrete=task.discrete)
    if task.discrete:
        action: dict[str, Any] = {"type": "discrete", "rule": "argmax", "n": task.n_a}
    else:
        if env is not None:
            low, high = env.action_space.low, env.action_space.high
        else:
            bounds = task.action_bounds()
            assert bounds is not None
            low, high = bounds
        action = {"type": "continuous", "rule": "clip", "low": _bound(low, task.n_a), "high": _bound(high, task.n_a)}
    adapter = task.observation
    observation = adapter.to_json() if isinstance(adapter, Selection) else {"names": list(adapter.names)}
    env_doc = env_document(task)
    network: dict[str, Any]
    if isinstance(pol, LinearPolicy):
        network = {"W": pol.W.tolist(), "b": pol.b.tolist()}
    else:
        network = {"policy": task.policy.to_json(), "forward": FORWARD_TEXT,
                   "layers": [{"W": W.tolist(), "b": b.tolist()} for W, b in pol.layers]}
    return {
        "format": FORMAT if isinstance(pol, LinearPolicy) else FORMAT_MLP,
        "task": task.name,
        "env_id": task.env_id if task.has_env else None,
        "env": env_doc,
        "observation": observation,
        "action": action,
        "n_s": task.n_s,
        "n_a": task.n_a,
        "action_type": task.action_type,
        **network,
        "theta": [float(v) for v in theta],
        "versions": _versions(((env_doc or {}).get("spec") or {}).get("entry_point")),
        "task_spec": task.spec.model_dump(mode="json") if task.spec is not None else None,
        "search": search,
        "final_eval": final_eval,
    }


def _format2_problem(doc: dict[str, Any], n_a: int) -> str:
    """What is wrong with a format-2 file's observation, action or env block, or "" (read_policy)."""
    try:
        Selection.from_json(doc["observation"])
    except (KeyError, TypeError, ValueError, AttributeError):
        return "the observation block is missing or not valid"
    spec = doc.get("task_spec")
    without_env = "env" in doc and doc["env"] is None and isinstance(spec, dict) and "env" in spec and spec["env"] is None
    if not without_env and not isinstance(doc.get("env"), dict):  # null only for a task without env
        return "the env block is missing or not an object"
    action = doc.get("action")
    rule = "argmax" if doc["action_type"] == "discrete" else "clip"
    if not isinstance(action, dict) or action.get("rule") != rule:
        return f"the action block's rule must be {rule!r} for action_type {doc['action_type']!r}"
    if rule == "clip":
        try:
            low, high = (np.asarray(action[k], dtype=np.float64) for k in ("low", "high"))
        except (KeyError, TypeError, ValueError):
            return f"a continuous action needs numeric low and high bounds of length n_a = {n_a}"
        if low.shape != (n_a,) or high.shape != (n_a,) or np.isnan(low).any() or np.isnan(high).any():
            return f"a continuous action needs numeric low and high bounds of length n_a = {n_a}"
        if (low > high).any():
            return "the action bounds have low > high"
    return ""


def read_policy(path: Path) -> tuple[dict[str, Any], np.ndarray]:
    """The policy file's document and its flat theta (shape (D,)).

    Raises:
        PPPropsError: missing, unreadable, not JSON, not a ppprops policy file, an action_type other
            than "discrete" or "continuous", or lacking a block (continuous actions: bounds of length n_a).
        ConfigError: W is not n_s x n_a, b not of length n_a, or a value is not finite.
    """
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PPPropsError(f"policy file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        from .fileio import read_error

        raise PPPropsError(f"policy file {path} cannot be read: {read_error(e)}") from None
    except json.JSONDecodeError as e:
        raise PPPropsError(f"policy file {path} is not JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(doc, dict) or doc.get("format") not in FORMATS:
        raise PPPropsError(f"policy file {path} is not a {FORMAT} or {FORMAT_MLP} document")
    if doc["format"] == FORMAT_MLP:
        return doc, _read_mlp(doc, path)
    missing = [k for k in ("n_s", "n_a", "W", "b") if k not in doc]
    if missing:
        raise PPPropsError(f"policy file {path} lacks {', '.join(missing)}")
    try:
        n_s, n_a = int(doc["n_s"]), int(doc["n_a"])
    except (TypeError, ValueError):
        raise PPPropsError(f"policy file {path}: n_s and n_a must be whole numbers, got {doc['n_s']!r}, {doc['n_a']!r}") from None
    try:
        W = np.asarray(doc["W"], dtype=np.float64)
        b = np.asarray(doc["b"], dtype=np.float64)
    except (TypeError, ValueError):
        raise PPPropsError(f"policy file {path}: W and b must hold numbers only (W a list of rows, b a list)") from None
    if W.shape != (n_s, n_a) or b.shape != (n_a,) or not (np.all(np.isfinite(W)) and np.all(np.isfinite(b))):
        raise ConfigError(f"policy file {path}: W must be {n_s}x{n_a} and b length {n_a}, all finite")
    if doc.get("action_type") not in ("discrete", "continuous"):
        raise PPPropsError(f"policy file {path}: action_type must be \"discrete\" or \"continuous\"")
    if doc["format"] == FORMAT:
        problem = _format2_problem(doc, n_a)
        if problem:
            raise PPPropsError(f"policy file {path}: {problem}")
    theta = np.concatenate([W.reshape(-1), b])
    assert theta.shape == (param_count(n_s, n_a),)
    return doc, theta


def _read_mlp(doc: dict[str, Any], path: Path) -> NDArray[np.float64]:
    """The flat theta of an MLP policy file, every block checked (``read_policy``)."""
    missing = [k for k in ("n_s", "n_a", "policy", "layers", "action_type") if k not in doc]
    if missing:
        raise PPPropsError(f"policy file {path} lacks {', '.join(missing)}")
    try:
        n_s, n_a = int(doc["n_s"]), int(doc["n_a"])
    except (TypeError, ValueError):
        raise PPPropsError(f"policy file {path}: n_s and n_a must be whole numbers, got {doc['n_s']!r}, {doc['n_a']!r}") from None
    try:
        spec = parse_policy(doc["policy"])
    except ValueError as e:
        raise PPPropsError(f"policy file {path}: {e}") from None
    if spec.is_linear:
        raise PPPropsError(f"policy file {path}: a {FORMAT_MLP} file holds an mlp policy, got {doc['policy']!r}")
    if doc.get("action_type") not in ("discrete", "continuous"):
        raise PPPropsError(f"policy file {path}: action_type must be \"discrete\" or \"continuous\"")
    shapes = spec.layer_shapes(n_s, n_a)
    layers = doc["layers"]
    if not isinstance(layers, list) or len(layers) != len(shapes):
        got = len(layers) if isinstance(layers, list) else type(layers).__name__
        raise ConfigError(f"policy file {path}: policy {spec.label()} has {len(shapes)} layers for n_s={n_s}, n_a={n_a}, got {got}")
    parts = []
    for number, (layer, (i, o)) in enumerate(zip(layers, shapes, strict=True), start=1):
        try:
            W = np.asarray(layer["W"], dtype=np.float64)
            b = np.asarray(layer["b"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise PPPropsError(f"policy file {path}: layer {number} must be {{\"W\": rows of numbers, \"b\": numbers}}") from None
        if W.shape != (i, o) or b.shape != (o,):
            raise ConfigError(f"policy file {path}: layer {number} must have W {i}x{o} and b of length {o} (policy {spec.label()}, "
                              f"n_s={n_s}, n_a={n_a}), got W {'x'.join(map(str, W.shape))} and b of length {b.size}")  # fmt: skip
        if not (np.all(np.isfinite(W)) and np.all(np.isfinite(b))):
            raise ConfigError(f"policy file {path}: layer {number} has a value that is not finite")
        parts += [W.reshape(-1), b]
    problem = _format2_problem(doc, n_a)
    if problem:
        raise PPPropsError(f"policy file {path}: {problem}")
    theta = np.concatenate(parts)
    assert theta.shape == (spec.param_count(n_s, n_a),)
    return theta


class Policy:
    """A deployable policy read from a policy file: call it on raw env observations.

    ``policy(obs)`` returns the action for one raw observation of the env the file records: an
    ``int`` for discrete actions (the argmax of u), a float64 array of shape (n_a,) clipped to the
    action bounds for continuous ones, where u = s @ W + b (paper Eq. 10, u = W^T s + b) and
    s = ``policy.state(obs)`` (shape (n_s,)). ``make_env()`` makes that env (``gym.make`` of the recorded EnvSpec). Only numpy is
    needed to act; gymnasium to make the env. An MLP file's policy (``spec``, a ``PolicySpec``) has
    ``layers`` ((W_l, b_l) pairs, input to output) and no single ``W``, ``b``; ``scores`` is its forward
    pass (``ppprops.policy.FORWARD_TEXT``).
    """

    def __init__(self, doc: dict[str, Any], theta: NDArray[np.float64], *, path: Path | None = None) -> None:
        self.document = doc
        self.path = path
        self.task: str = str(doc.get("task"))
        self.theta = theta
        self.n_s, self.n_a = int(doc["n_s"]), int(doc["n_a"])
        self.spec: PolicySpec = parse_policy(doc["policy"]) if doc["format"] == FORMAT_MLP else LINEAR
        self.discrete = doc["action_type"] == "discrete"
        if doc["format"] in (FORMAT, FORMAT_MLP):
            self.selection = Selection.from_json(doc["observation"])
            action = doc["action"]
            self.low = None if self.discrete else np.asarray(action["low"], dtype=np.float64)
            self.high = None if self.discrete else np.asarray(action["high"], dtype=np.float64)
        else:  # a /1 file names its task only: the adapter and bounds come from the task registry
            from .tasks import get_task

            task = get_task(self.task)
            self.selection = task.observation  # type: ignore[assignment]
            self.low = self.high = None
            if not self.discrete:
                env = task.make_env()
                self.low, self.high = np.asarray(env.action_space.low, np.float64), np.asarray(env.action_space.high, np.float64)
                env.close()

        self.network: LinearPolicy | MLPPolicy = make_network(theta, self.spec, self.n_s, self.n_a, discrete=self.discrete,
                                                               low=self.low, high=self.high)  # fmt: skip

    @property
    def W(self) -> NDArray[np.float64]:
        """Weights of u = s @ W + b, shape (n_s, n_a). Raises AttributeError for an MLP (``layers``)."""
        if not isinstance(self.network, LinearPolicy):
            raise AttributeError(f"policy file {self.path} holds an {self.spec.label()} policy: it has layers, not one W")
        return self.network.W

    @property
    def b(self) -> NDArray[np.float64]:
        """Bias of u = s @ W + b, shape (n_a,). Raises AttributeError for an MLP (``layers``)."""
        if not isinstance(self.network, LinearPolicy):
            raise AttributeError(f"policy file {self.path} holds an {self.spec.label()} policy: it has layers, not one b")
        return self.network.b

    @property
    def layers(self) -> tuple[tuple[NDArray[np.float64], NDArray[np.float64]], ...]:
        """(W_l, b_l) of each layer, input to output; ((W, b),) for a linear policy."""
        if isinstance(self.network, LinearPolicy):
            return ((self.network.W, self.network.b),)
        return self.network.layers

    @property
    def names(self) -> tuple[str, ...]:
        """One name per state value, in the order of s."""
        return tuple(self.selection.names)

    def state(self, obs: Any) -> NDArray[np.float64]:
        """The policy's state s (shape (n_s,)) from one raw observation."""
        return self.selection(obs)

    def scores(self, obs: Any) -> NDArray[np.float64]:
        """u = s @ W + b (an MLP: its forward pass), shape (n_a,)."""
        return self.network.scores(self.state(obs))

    def __call__(self, obs: Any) -> int | NDArray[np.float64]:
        """The action for one raw observation: argmax of u (discrete) or u clipped to the action bounds."""
        u = self.scores(obs)
        if self.discrete:
            return int(np.argmax(u))
        assert self.low is not None and self.high is not None
        return np.clip(u, self.low, self.high)

    def make_env(self, **kwargs: Any) -> Any:
        """The env this policy was searched on (``kwargs`` go to ``gym.make``, e.g. ``render_mode``).

        Raises:
            ConfigError: the file records no portable env (its factory had no importable name), or
                its task has no env (a robot outside Python: apply the policy to its observations).
        """
        if self.document["format"] == FORMAT_V1:
            from .tasks import get_task

            return get_task(self.task).make_env()
        import gymnasium as gym
        from gymnasium.envs.registration import EnvSpec

        env_doc = self.document["env"]
        if env_doc is None:
            raise ConfigError(f"policy file {self.path}: task {self.task} has no env (a robot outside Python): there is "
                              "no env to make; call the policy on the robot's observations")  # fmt: skip
        if env_doc.get("spec") is None:
            raise ConfigError(f"policy file {self.path}: its env was made by a factory with no importable name; make it yourself")
        for folder in env_doc.get("paths", ()):
            if folder not in sys.path:
                sys.path.append(folder)
        for module in env_doc.get("imports", ()):
            importlib.import_module(module)
        return gym.make(EnvSpec.from_json(json.dumps(env_doc["spec"])), **kwargs)

    def __repr__(self) -> str:
        kind = "discrete" if self.discrete else "continuous"
        family = "" if self.spec.is_linear else f", policy={self.spec.label()!r}"
        return f"Policy(task={self.task!r}, n_s={self.n_s}, n_a={self.n_a}{family}, {kind})"


def load_policy(path: str | os.PathLike[str]) -> Policy:
    """Read a policy file (``best_policy.json``) into a callable ``Policy`` (raw observation -> action).

    Raises:
        PPPropsError: the file is missing, not JSON, or not a valid ppprops policy file.
        ConfigError: its W or b has the wrong shape or a non-finite value.
        UnknownTaskError: a ``/1`` file whose task this ppprops does not know.
    """
    doc, theta = read_policy(Path(path))
    return Policy(doc, theta, path=Path(path))
