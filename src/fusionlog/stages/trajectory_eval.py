"""The evaluator's trajectory metrics (DESIGN.md "Trajectory metrics"): APE and RPE of each
architecture after the scenario's alignment, for replays and simulations alike.

Each block's runs are aligned and measured one by one (`core.trajectory.block_sums`); the sums
merge in block order. The evaluator calls `add` with a block's truth and means (or `merge`
with sums made elsewhere: a Dask worker's), then `summary` per architecture and `recording`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.trajectory import AlignmentError, TrajectorySums, block_sums
from fusionlog.errors import FusionlogError

__all__ = ["trajectory_block"]


def trajectory_block(
    sc: Any,
    times: np.ndarray,
    truth: np.ndarray,
    means: dict[str, np.ndarray],
    run_offset: int,
    source: str,
) -> dict[str, TrajectorySums] | None:
    """The trajectory sums of a block (None: the scenario has no position states); an
    alignment that cannot be fitted is a one-line FusionlogError naming `source`."""
    if sc.trajectory is None:
        return None
    try:
        return block_sums(sc.trajectory, times, truth, means, run_offset, sc.runs > 1)
    except AlignmentError as e:
        raise FusionlogError(f"{source}: {e}") from None
