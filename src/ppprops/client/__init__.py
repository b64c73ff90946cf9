"""The client's side of the trust boundary: secrets and the codec that produces wire values.

``Codec`` and ``Secrets`` load with their module on first use (reading a key file needs no codec).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .codec import Codec
    from .secrets import Secrets

__all__ = ["Codec", "Secrets"]


def __getattr__(name: str) -> Any:
    if name == "Codec":
        from .codec import Codec

        return Codec
    if name == "Secrets":
        from .secrets import Secrets

        return Secrets
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
