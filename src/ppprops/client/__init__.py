"""The client's side of the trust boundary: secrets and the codec that produces wire values."""

from .codec import Codec
from .secrets import Secrets

__all__ = ["Codec", "Secrets"]
