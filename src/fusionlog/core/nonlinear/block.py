"""`core.architectures.estimate_block` for a nonlinear system: the EKF/UKF architectures on a
block of runs (`architectures.estimate`) and, given the truth, the block's metric sums."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..architectures.block import Block, PlanCache
from ..architectures.plan import Estimate
from .architectures import estimate


def nonlinear_block(
    cache: PlanCache,
    archs: Sequence[str],
    z: np.ndarray,
    truth: np.ndarray | None,
    workspace: Any,
    keep: bool,
    run_offset: int,
) -> Block:
    """Each architecture's estimates of the block z (runs, K+1, m) on the cache's system and
    instants (its system is on them: `PlanCache.of`), and their metric sums given the truth."""
    system, times = cache.system, cache.times
    sums: dict[str, Any] | None = None
    if truth is not None:
        from ..metrics import MetricsAccumulator, MetricsWorkspace  # scipy: on first use only

        sums, detached = {}, MetricsWorkspace()
    estimates: dict[str, Estimate] = {}
    for a in archs:
        tr = estimate(system, a, z, times, run_offset)
        if keep:
            estimates[a] = Estimate(tr.mean, tr.cov)
        if sums is not None:
            acc = MetricsAccumulator(truth.shape[1], truth.shape[2], workspace=workspace)
            acc.add(truth, tr.mean, tr.cov)
            acc.workspace = detached
            sums[a] = acc
    return Block(estimates, None, sums, None)
