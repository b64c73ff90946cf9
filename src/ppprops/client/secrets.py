"""Per-run secrets: the diagonal A and the reward scale c, kept in a 0600 key file in the run directory.

Distribution (documented in docs/privacy.md): each a_j and c is drawn independently and
log-uniformly from [0.1, 10] (ln a_j ~ U(ln 0.1, ln 10)), from the operating system's entropy
source, never from the run seed, so two runs with the same seed still get different secrets.

Hardened runs (docs/threat-model.md) add three optional secrets: raw origins ``m`` (one per
parameter) and ``s`` (for rewards), and the reward warp exponent ``p``. Key files without them
(every file written before they existed) still load, with the neutral values m = 0, s = 0, p = 1,
and keep their fingerprint.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import os
import secrets as _os_secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import KeyFileError

LOG_LOW, LOG_HIGH = math.log(0.1), math.log(10.0)
KEY_FORMAT = "ppprops.secrets/1"
SUBKEY_TAG = b"ppprops.subkey/1\x00"

# pp-hardened: a_j is a scale of the warped coordinate (slope at the box centre); a narrower range
# keeps the warm-up's raw spread useful (see docs/threat-model.md, "cost").
HARDENED_A_LOG = (math.log(1 / 3), math.log(3.0))
# |ln p| ~ U(ln 1.25, ln 2) with a random sign: p is never near 1, so integer returns never keep
# a lattice that the gcd attack could read.
HARDENED_P_LOG = (math.log(1.25), math.log(2.0))


def os_rng() -> np.random.Generator:
    """A generator seeded with 128 bits from the operating system's entropy source."""
    return np.random.default_rng(_os_secrets.randbits(128))


def portable(x: Any) -> NDArray[np.float64]:
    """``x`` (a number or an array) rounded to 12 significant digits, as float64.

    Secrets drawn through ``np.exp`` may differ in their last bits between numpy builds, and every
    keyed draw hashes the secrets' exact values (``Secrets.subkey``), so unrounded a master key or
    a seeded generator would give other keyed draws on another machine. Rounded, they agree
    (unless a value lies within a last bit of a rounding boundary). A key file stores the values
    exactly, so a run reads back the same secrets wherever it is resumed.
    """
    return np.asarray([float(f"{v:.12g}") for v in np.ravel(x)], dtype=np.float64).reshape(np.shape(x))


@dataclass(frozen=True, repr=False, eq=False)
class Secrets:
    """A run's secrets, kept only in its key file: the diagonal ``a`` of A (shape (D,), all > 0) and
    the reward scale ``c`` > 0 (paper Eq. 4-5, 7), plus the hardening extras (docs/threat-model.md):
    parameter origins ``m`` (shape (D,)), reward origin ``s``, warp exponent ``p``. Never printed.
    """

    run_id: str
    a: NDArray[np.float64]  # diagonal of A, all > 0
    c: float  # reward scale, > 0
    m: NDArray[np.float64] | None = None  # raw parameter origins (secret_offsets); None = 0
    s: float | None = None  # raw reward origin (secret_offsets); None = 0
    p: float | None = None  # reward warp exponent (warp_rewards); None = 1

    def __repr__(self) -> str:  # never print secret values by accident
        extra = ", hardened" if self.has_extras else ""
        return f"Secrets(run_id={self.run_id!r}, D={len(self.a)}{extra}, <hidden>)"

    __str__ = __repr__

    @property
    def has_extras(self) -> bool:
        """True when any hardening extra (m, s, p) is set."""
        return self.m is not None or self.s is not None or self.p is not None

    @property
    def origin(self) -> NDArray[np.float64]:
        """The raw parameter origin m, shape (D,); zeros without ``secret_offsets``."""
        return np.zeros(len(self.a)) if self.m is None else np.asarray(self.m, dtype=np.float64)

    @property
    def reward_origin(self) -> float:
        """The raw reward origin s (reward units); 0 without ``secret_offsets``."""
        return 0.0 if self.s is None else float(self.s)

    @property
    def exponent(self) -> float:
        """The reward warp exponent p; 1 without ``warp_rewards``."""
        return 1.0 if self.p is None else float(self.p)

    @classmethod
    def generate(cls, run_id: str, D: int, *, rng: np.random.Generator | None = None) -> Secrets:
        """The paper's secrets: A and c only. ``rng`` None: from the OS entropy source."""
        rng = os_rng() if rng is None else rng
        a = portable(np.exp(rng.uniform(LOG_LOW, LOG_HIGH, size=D)))
        c = float(portable(np.exp(rng.uniform(LOG_LOW, LOG_HIGH))))
        return cls(run_id=run_id, a=a, c=c)

    @classmethod
    def generate_hardened(
        cls, run_id: str, D: int, *, box: tuple[float, float], reward_scale: float, rng: np.random.Generator | None = None
    ) -> Secrets:
        """pp-hardened secrets (``rng`` None: from the OS entropy source).

        a_j log-uniform on [1/3, 3]; m_j uniform on the central half of the box; c log-uniform on
        [0.1, 10]; s uniform on [-reward_scale, reward_scale]; p = exp(+-U(ln 1.25, ln 2)).
        """
        rng = os_rng() if rng is None else rng
        lo, hi = box
        mid, quarter = (lo + hi) / 2.0, (hi - lo) / 4.0
        a = portable(np.exp(rng.uniform(*HARDENED_A_LOG, size=D)))
        m = rng.uniform(mid - quarter, mid + quarter, size=D)
        c = float(portable(np.exp(rng.uniform(LOG_LOW, LOG_HIGH))))
        s = float(rng.uniform(-abs(reward_scale), abs(reward_scale)))
        p = float(portable(np.exp(rng.choice([-1.0, 1.0]) * rng.uniform(*HARDENED_P_LOG))))
        return cls(run_id=run_id, a=a, c=c, m=m, s=s, p=p)

    def subkey(self, purpose: str) -> bytes:
        """A 32-byte key for one purpose, derived from every secret value (never from the run seed).

        Used for what must be secret but need not be stored: the request's sampling seed, the
        reward dither and the per-component reward maps of pp-hardened (docs/threat-model.md).
        Deterministic for a key file, so ``resume`` derives the same; distinct from
        ``fingerprint()`` (which the store keeps) by a tag, so the fingerprint does not give it.
        """
        blob = json.dumps(self._payload(), sort_keys=True).encode()
        return hmac.new(hashlib.sha256(SUBKEY_TAG + blob).digest(), purpose.encode(), hashlib.sha256).digest()

    def _payload(self) -> dict[str, object]:
        out: dict[str, object] = {"format": KEY_FORMAT, "run_id": self.run_id, "a": [float(v) for v in self.a], "c": self.c}
        # optional keys only when set, so a paper key keeps the payload (and fingerprint) it always had
        if self.m is not None:
            out["m"] = [float(v) for v in self.m]
        if self.s is not None:
            out["s"] = float(self.s)
        if self.p is not None:
            out["p"] = float(self.p)
        return out

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
        """Read the key file at ``path`` and check it belongs to ``run_id`` with ``D`` parameters.

        ``fingerprint``: the one the store recorded at the start; a different key is refused.
        Raises KeyFileError (one line) for a missing, unreadable, corrupt, foreign or replaced file.
        """
        try:
            raw = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise KeyFileError(f"key file {path} is missing; the run cannot be resumed without it") from None
        except UnicodeDecodeError as e:
            from ..fileio import read_error

            raise KeyFileError(f"key file {path} is corrupt: {read_error(e)}") from None
        except OSError as e:
            raise KeyFileError(f"key file {path} cannot be read: {e.strerror or e.__class__.__name__}") from None
        except json.JSONDecodeError:
            raise KeyFileError(f"key file {path} is corrupt (not JSON)") from None
        try:
            if raw.get("format") != KEY_FORMAT:
                raise ValueError("format")
            a = np.asarray(raw["a"], dtype=np.float64)
            c = float(raw["c"])
            rid = str(raw["run_id"])
            m = np.asarray(raw["m"], dtype=np.float64) if "m" in raw else None
            s = float(raw["s"]) if "s" in raw else None
            p = float(raw["p"]) if "p" in raw else None
        except (KeyError, TypeError, ValueError, AttributeError):
            raise KeyFileError(f"key file {path} is corrupt (missing or malformed fields)") from None
        if a.shape != (D,) or not np.all(np.isfinite(a)) or np.any(a <= 0) or not (math.isfinite(c) and c > 0):
            raise KeyFileError(f"key file {path} is corrupt (values out of range for D={D})")
        if (m is not None and (m.shape != (D,) or not np.all(np.isfinite(m)))) or (s is not None and not math.isfinite(s)) \
                or (p is not None and not (math.isfinite(p) and p > 0)):
            raise KeyFileError(f"key file {path} is corrupt (hardening values out of range for D={D})")
        if rid != run_id:
            raise KeyFileError(f"key file {path} belongs to run {rid}, not to run {run_id}")
        secrets = cls(run_id=rid, a=a, c=c, m=m, s=s, p=p)
        if fingerprint is not None and secrets.fingerprint() != fingerprint:
            raise KeyFileError(f"key file {path} does not match the key this run was started with")
        return secrets
