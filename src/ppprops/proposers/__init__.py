"""Proposers speak ask/tell; the study (``ppprops.study``) evaluates, records and reports for all of them."""

from .base import Proposal, Proposer
from .llm import LLMProposer
from .uniform import UniformSampler

__all__ = ["LLMProposer", "Proposal", "Proposer", "UniformSampler"]
