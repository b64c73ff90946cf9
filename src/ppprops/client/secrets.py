"""Per-run secrets: the diagonal A and the reward scale c, kept in a 0600 key file in the run directory.

Distribution (documented in docs/privacy.md): each a_j and c is drawn independently and
log-uniformly from [0.1, 10] (ln a_j ~ U(ln 0.1, ln 10)), from the operating system's entropy
source, never from the run seed, so two runs with the same seed still get different secrets.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import secrets as _os_secrets
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import KeyFileError

LOG_LOW, LOG_HIGH = math.log(0.1), math.log(10.0)
KEY_FORMAT = "ppprops.secrets/1"


@dataclass(frozen=True, repr=False, eq=False)
class Secrets:
    run_id: str
    a: NDArray[np.float64]  # diagonal of A, all > 0
    c: float  # reward scale, > 0

    def __repr__(self) -> str:  # never print secret values by accident
        return f"Secrets(run_id={self.run_id!r}, D={len(self.a)}, <hidden>)"

    __str__ = __repr__

    @classmethod
    def generate(cls, run_id: str, D: int) -> Secrets:
        rng = np.random.default_rng(_os_secrets.randbits(128))
        a = np.exp(rng.uniform(LOG_LOW, LOG_HIGH, size=D))
        c = float(np.exp(rng.uniform(LOG_LOW, LOG_HIGH)))
        return cls(run_id=run_id, a=a, c=c)

    def _payload(self) -> dict[str, object]:
        return {"format": KEY_FORMAT, "run_id": self.run_id, "a": [float(v) for v in self.a], "c": self.c}

    def fingerprint(self) -> str:
        """A digest that lets the store check a key file belongs to its run, without holding the key."""
        blob = json.dumps(self._payload(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()

    def save(self, path: Path) -> None:
        """Create the key file with mode 0600 from the start (never world-readable, even briefly)."""
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(self._payload(), f)
            f.flush()
            os.fsync(f.fileno())

    @classmethod
    def load(cls, path: Path, *, run_id: str, D: int, fingerprint: str | None = None) -> Secrets:
        try:
            raw = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise KeyFileError(f"key file {path} is missing; the run cannot be resumed without it") from None
        except (OSError, UnicodeDecodeError) as e:
            raise KeyFileError(f"key file {path} cannot be read: {e.__class__.__name__}") from None
        except json.JSONDecodeError:
            raise KeyFileError(f"key file {path} is corrupt (not JSON)") from None
        try:
            if raw.get("format") != KEY_FORMAT:
                raise ValueError("format")
            a = np.asarray(raw["a"], dtype=np.float64)
            c = float(raw["c"])
            rid = str(raw["run_id"])
        except (KeyError, TypeError, ValueError, AttributeError):
            raise KeyFileError(f"key file {path} is corrupt (missing or malformed fields)") from None
        if a.shape != (D,) or not np.all(np.isfinite(a)) or np.any(a <= 0) or not (math.isfinite(c) and c > 0):
            raise KeyFileError(f"key file {path} is corrupt (values out of range for D={D})")
        if rid != run_id:
            raise KeyFileError(f"key file {path} belongs to run {rid}, not to run {run_id}")
        s = cls(run_id=rid, a=a, c=c)
        if fingerprint is not None and s.fingerprint() != fingerprint:
            raise KeyFileError(f"key file {path} does not match the key this run was started with")
        return s
