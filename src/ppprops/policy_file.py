"""The deployable result: ``best_policy.json``, a linear policy with no encoding involved.

Format ``ppprops.linear_policy/1``::

    {
      "format": "ppprops.linear_policy/1",
      "task": "CartPole",            # ppprops task name (gives the observation adapter)
      "env_id": "CartPole-v1",
      "n_s": 4, "n_a": 2, "action_type": "discrete",
      "observation": ["cart_position", ...],   # names of s[0..n_s-1]
      "W": [[...n_a values...], ... n_s rows],  # u = W^T s + b
      "b": [...n_a values...],
      "theta": [...D values...],                # the same numbers in the flat layout
      "search": {"run_id": ..., "method": ..., "seed": ..., "return": ..., "candidate": ...},
      "final_eval": {"mean": ..., "std": ..., "episodes": ..., "seed": ...}
    }
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ConfigError, PPPropsError
from .policy import LinearPolicy, param_count
from .tasks.base import Task

FORMAT = "ppprops.linear_policy/1"


def policy_document(task: Task, theta: np.ndarray, *, search: dict[str, Any], final_eval: dict[str, Any] | None) -> dict[str, Any]:
    pol = LinearPolicy.from_flat(theta, task.n_s, task.n_a, discrete=task.discrete)
    return {
        "format": FORMAT,
        "task": task.name,
        "env_id": task.env_id,
        "n_s": task.n_s,
        "n_a": task.n_a,
        "action_type": task.action_type,
        "observation": list(task.observation.names),
        "W": pol.W.tolist(),
        "b": pol.b.tolist(),
        "theta": [float(v) for v in theta],
        "search": search,
        "final_eval": final_eval,
    }


def write_json_atomic(path: Path, doc: dict[str, Any]) -> None:
    """Write to a temp file in the same folder, then rename: a crash never leaves half a file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # a policy is meant to be deployed; only the key file is private
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_policy(path: Path) -> tuple[dict[str, Any], np.ndarray]:
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PPPropsError(f"policy file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PPPropsError(f"policy file {path} cannot be read as JSON ({e.__class__.__name__})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise PPPropsError(f"policy file {path} is not a {FORMAT} document")
    try:
        n_s, n_a = int(doc["n_s"]), int(doc["n_a"])
        W = np.asarray(doc["W"], dtype=np.float64)
        b = np.asarray(doc["b"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise PPPropsError(f"policy file {path} lacks n_s, n_a, W or b") from None
    if W.shape != (n_s, n_a) or b.shape != (n_a,) or not (np.all(np.isfinite(W)) and np.all(np.isfinite(b))):
        raise ConfigError(f"policy file {path}: W must be {n_s}x{n_a} and b length {n_a}, all finite")
    theta = np.concatenate([W.reshape(-1), b])
    assert theta.shape == (param_count(n_s, n_a),)
    return doc, theta
