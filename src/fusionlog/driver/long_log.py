"""A long one-run log estimated in blocks of time (issue 34: 10^6 instants in bounded memory).

The readings are spooled once to an unnamed temporary file (`Spool`: (K+1, m) doubles, 24 MB
per 10^6 instants of three scalar sensors, on disk, not in memory); FBS's backward pass
(`core.architectures.long_log.SteadyLog.backward`) reads them back block by block from the
log's end and writes its information vectors to a second spool; the forward pass then reads
both block by block and hands each block's estimates over (`long_estimates`). Memory: one
block of readings, estimates and covariances, whatever the log's length. The block size is
`time_block()` instants (the environment variable FUSIONLOG_TIME_BLOCK, a hidden setting
that lets a test cut a short log into several blocks).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from fusionlog.core.architectures import Estimate
from fusionlog.core.architectures.long_log import SteadyLog

__all__ = ["TIME_BLOCK_ENV", "Spool", "long_estimates", "spool_readings", "time_block"]

#: Instants per block of time (environment), and the default.
TIME_BLOCK_ENV = "FUSIONLOG_TIME_BLOCK"
TIME_BLOCK = 1 << 16


def time_block() -> int:
    """Instants per block of a long one-run log: FUSIONLOG_TIME_BLOCK when it is a positive
    integer, else `TIME_BLOCK` (64 Ki instants: a few megabytes per block)."""
    text = os.environ.get(TIME_BLOCK_ENV, "")
    return int(text) if text.strip().isdigit() and int(text) > 0 else TIME_BLOCK


class Spool:
    """Rows of `width` doubles in an unnamed temporary file (deleted when closed), written and
    read back by blocks of instants."""

    def __init__(self, width: int) -> None:
        self.width = width
        self.file = tempfile.TemporaryFile(prefix="fusionlog-spool-")

    def write(self, k0: int, rows: np.ndarray) -> None:
        self.file.seek(k0 * self.width * 8)
        self.file.write(np.ascontiguousarray(rows, dtype="<f8").tobytes())

    def read(self, k0: int, k1: int) -> np.ndarray:
        self.file.seek(k0 * self.width * 8)
        data = self.file.read((k1 - k0) * self.width * 8)
        return np.frombuffer(data, "<f8").reshape(k1 - k0, self.width).copy()

    def close(self) -> None:
        self.file.close()


def spool_readings(
    blocks: Iterable[tuple[int, int, dict[str, Any]]],
    topics: list[str],
    width: int,
    missing: bool = False,
) -> Spool | None:
    """The stacked readings z_k of eq. (30) of a log read in blocks of time, spooled; None
    (nothing kept) when one is missing: the short plans stand only for a complete log
    (`missing`: kept as NaN, for filters that take each instant as it comes)."""
    spool = Spool(width)
    for k0, _k1, data in blocks:
        z = np.concatenate([data[t][0] for t in topics], axis=-1)
        if not missing and np.isnan(z).any():
            spool.close()
            return None
        spool.write(k0, z)
    return spool


def long_estimates(
    log: SteadyLog, readings: Spool, block: int
) -> Iterator[tuple[int, int, dict[str, Estimate]]]:
    """(k0, k1, {arch: Estimate}) of each block of time of the spooled log, in order: mean
    (1, w, n), cov (w, n, n) shared. The spools are closed at the end."""
    K1 = log.steps + 1
    edges = [(k0, min(k0 + block, K1)) for k0 in range(0, K1, block)]
    backward: dict[str, Spool] = {}
    try:
        for a, plan in log.plans.items():
            if plan.smoother is None:
                continue
            spool = backward[a] = Spool(plan.smoother.B[0].shape[-1])
            carried = None
            for k0, k1 in reversed(edges):
                y, carried = log.backward(a, readings.read(k0, k1)[None], k0, carried)
                spool.write(k0, y)
        for k0, k1 in edges:
            z = readings.read(k0, k1)[None]
            out = {}
            for a in log.plans:
                yb = backward[a].read(k0, k1) if a in backward else None
                out[a] = Estimate(log.forward(a, z, k0, yb), log.cov(a, k0, k1))
            yield k0, k1, out
    finally:
        for s in backward.values():
            s.close()
        readings.close()
