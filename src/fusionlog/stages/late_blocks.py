"""A long one-run log with late sensors whose delays are drawn or recorded, or whose readings
are missing, in blocks of time (issue 34): the sensors file read block by block -- its readings
(spooled, `driver.long_log`) and the arrival field of its late sensors' messages
(`io.mcap.arrival.iter_arrival_blocks`) -- through `core.latency_blocks.LateBlocks`.

The arrivals are those `state_kind.recorded_arrivals` reads for the whole run
(`io.mcap.arrival.message_arrivals`): a late sensor's from its messages, a message without the
field on time (NaN where it has no message: no reading), a sensor on time at its instants.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from fusionlog.core.late_policy import random_delays
from fusionlog.core.latency_blocks import LateBlocks
from fusionlog.core.model import System
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile

__all__ = ["arrival_blocks", "late_estimates"]


def arrival_blocks(
    sensors: McapFile, system: System, topics: list[str], block: int
) -> Iterator[np.ndarray | None]:
    """Each block of time's arrival times (w, S) s, in order; None per block where the delays
    are fixed (the model says when)."""
    from fusionlog.io.mcap.arrival import iter_arrival_blocks

    times = sensors.times()
    K1 = len(times)
    if not random_delays(system):
        for _ in range(0, K1, block):
            yield None
        return
    late = [j for j, s in enumerate(system.sensors) if s.timing.late]
    got = iter_arrival_blocks(sensors.path, [topics[j] for j in late], K1, block)
    for k0, k1, a in got:
        out = np.repeat(times[k0:k1, None], len(topics), axis=1)
        out[:, late] = a
        yield out


def late_estimates(
    blocks: LateBlocks, sensors: McapFile, system: System, topics: list[str], spool: Any, B: int
) -> Iterator[tuple[int, int, dict[str, Any]]]:
    """(k0, k1, {arch: Estimate}) of each block of time of the spooled readings (closed at the
    end); a reading arriving outside its sensor's latency range names the file."""
    from fusionlog.driver.long_log import edges

    try:
        arrivals = arrival_blocks(sensors, system, topics, B)
        for (k0, k1), arrival in zip(edges(blocks.late.steps + 1, B), arrivals, strict=True):
            try:
                got = blocks.estimates(k0, k1, spool.read(k0, k1), arrival)
            except ValueError as e:
                raise FusionlogError(f"{sensors.path}: {e}") from None
            yield k0, k1, got
    finally:
        spool.close()
