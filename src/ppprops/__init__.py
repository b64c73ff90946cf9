"""ppprops: Privacy-Preserving Prompted Policy Search (PP-ProPS).

An LLM proposes linear-policy parameters from an encoded history; the client keeps the policy,
the rewards and the secrets. See ``ppprops.runner`` for the programmatic entry points.
"""

__version__ = "0.1.0"
