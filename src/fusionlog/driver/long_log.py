"""A long one-run log estimated in blocks of time (issue 34: 10^6 instants in bounded memory).

The readings are spooled once to an unnamed temporary file (`Spool`: (K+1, m) doubles, 24 MB
per 10^6 instants of three scalar sensors, on disk, not in memory); FBS's backward pass
(`core.architectures.long_log.SteadyLog.backward`) reads them back block by block from the
log's end and writes its information vectors to a second spool; the forward pass then reads
both block by block and hands each block's estimates over (`long_estimates`). Memory: one
block of readings, estimates and covariances, whatever the log's length. The block size is
`time_block()` instants (the environment variable FUSIONLOG_TIME_BLOCK, a hidden setting
that lets a test cut a short log into several blocks).

A recorded replay (irregular instants, per-message R, missing readings: no steady plans) goes
the same way through the plan-free path carried block to block
(`core.architectures.replay_blocks.ReplayBlocks`, `replay_long_estimates`): its readings, NaN
where missing, spooled once; FBS's backward information filter run from the log's end over
them, its vectors y_b and matrices S (n + n^2 doubles per instant) **written to a second
unnamed temporary file** (`backward_spool`) and read back by the forward pass.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from fusionlog.core.architectures import Estimate
from fusionlog.core.architectures.long_log import SteadyLog
from fusionlog.core.architectures.replay_blocks import ReplayBlocks

__all__ = [
    "TIME_BLOCK_ENV",
    "Spool",
    "backward_spool",
    "edges",
    "long_estimates",
    "replay_long_estimates",
    "spool_readings",
    "time_block",
]

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
        self.missing = False  # some row has a NaN (`spool_readings`)

    def write(self, k0: int, rows: np.ndarray) -> None:
        self.file.seek(k0 * self.width * 8)
        self.file.write(np.ascontiguousarray(rows, dtype="<f8").tobytes())

    def read(self, k0: int, k1: int) -> np.ndarray:
        self.file.seek(k0 * self.width * 8)
        data = self.file.read((k1 - k0) * self.width * 8)
        return np.frombuffer(data, "<f8").reshape(k1 - k0, self.width).copy()

    def present(self, block: int) -> np.ndarray:
        """Where the spooled rows are not NaN, (rows, width) bool, read back block by block
        (the readings' measurement pattern: one byte per component and instant)."""
        rows = self.file.seek(0, 2) // (8 * self.width)
        out = np.empty((rows, self.width), dtype=bool)
        for k0, k1 in edges(rows, block):
            out[k0:k1] = ~np.isnan(self.read(k0, k1))
        return out

    def close(self) -> None:
        self.file.close()


def spool_readings(
    blocks: Iterable[tuple[int, int, dict[str, Any]]], topics: list[str], width: int
) -> Spool:
    """The stacked readings z_k of eq. (30) of a log read in blocks of time, spooled, NaN
    where missing (`Spool.missing`: the short plans stand only for a complete log)."""
    spool = Spool(width)
    for k0, _k1, data in blocks:
        z = np.concatenate([data[t][0] for t in topics], axis=-1)
        spool.missing |= bool(np.isnan(z).any())
        spool.write(k0, z)
    return spool


def edges(instants: int, block: int) -> list[tuple[int, int]]:
    """The blocks of time [k0, k1) of a log of `instants`."""
    return [(k0, min(k0 + block, instants)) for k0 in range(0, instants, block)]


def backward_spool(
    blocks: ReplayBlocks, readings: Callable[[int, int], np.ndarray], block: int
) -> Spool:
    """FBS's backward vectors y_b and matrices S of every instant (`ReplayBlocks.backward`, the
    blocks from the log's end), spooled: a row [y_b, S.ravel()] per instant. `readings(k0,
    k1)`: the block's z (w, m), NaN where missing."""
    n = blocks.system.n
    spool = Spool(n + n * n)
    after = None
    try:
        for k0, k1 in reversed(edges(blocks.steps + 1, block)):
            yb, S, after = blocks.backward(k0, k1, readings(k0, k1), after)
            spool.write(k0, np.concatenate([yb, S.reshape(len(yb), -1)], axis=1))
    except BaseException:
        spool.close()
        raise
    return spool


def read_backward(spool: Spool, k0: int, k1: int) -> tuple[np.ndarray, np.ndarray]:
    """(y_b (w, n), S (w, n, n)) of the instants k0..k1-1 from `backward_spool`'s file."""
    rows = spool.read(k0, k1)
    n = round((4 * spool.width + 1) ** 0.5 - 1) // 2
    return rows[:, :n], rows[:, n:].reshape(len(rows), n, n)


def replay_long_estimates(
    blocks: ReplayBlocks, readings: Spool, block: int
) -> Iterator[tuple[int, int, dict[str, Estimate]]]:
    """(k0, k1, {arch: Estimate}) of each block of time of a spooled one-run replay, in order
    (`ReplayBlocks`: mean (1, w, n), cov (w, n, n)); FBS's backward pass first, spooled. The
    spools are closed at the end."""
    backward = None
    try:
        if blocks.smoother:
            backward = backward_spool(blocks, lambda a, b: readings.read(a, b), block)
        for k0, k1 in edges(blocks.steps + 1, block):
            bw = read_backward(backward, k0, k1) if backward is not None else None
            yield k0, k1, blocks.estimates(k0, k1, readings.read(k0, k1), bw)
    finally:
        if backward is not None:
            backward.close()
        readings.close()


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
