"""The estimation driver, above the math of `core`: a block of runs through the architectures
(`estimate_block`) with the plans kept across blocks (`PlanCache`, and `KeptPlans` between two
stages of one command), each passed explicitly by the caller."""

from .block import Block, conditional_sums, estimate_block
from .plans import KeptPlans, PlanCache, pattern_record

__all__ = [
    "Block",
    "KeptPlans",
    "PlanCache",
    "conditional_sums",
    "estimate_block",
    "pattern_record",
]
