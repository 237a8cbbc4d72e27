"""The estimation driver, above the math of `core`: a block of runs through the architectures
(`estimate_block`) with the plans kept across blocks (`PlanCache`, `KeptPlans` between two
stages of one command, `JobPlans` across the jobs of a process), each passed explicitly by the
caller."""

from .block import Block, conditional_sums, estimate_block
from .plans import JobPlans, KeptPlans, PlanCache, pattern_record

__all__ = [
    "Block",
    "JobPlans",
    "KeptPlans",
    "PlanCache",
    "conditional_sums",
    "estimate_block",
    "pattern_record",
]
