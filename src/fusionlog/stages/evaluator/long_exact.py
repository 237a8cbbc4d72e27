"""The exact analysis of a long recorded replay in blocks of time (issue 34): the one-log route
(`core.exact_replay`, the truth the filters' model) carried from block to block, for logs
without steady plans (irregular instants, per-message R, missing readings).

FBS's exact values need its backward information filter's S at each instant, which runs from
the log's end: `prepare` runs it over the blocks in reverse order first and spools S (with
y_b, unused here) to an unnamed temporary file (`driver.long_log.backward_spool`), read back
block by block. The bound check's worst instant is followed as the blocks come
(`BoundStream`), so nothing of the size of the log is kept but the measurement mask (one byte
per component and instant, from the estimates' provenance).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.bound import BOUND_TOL
from fusionlog.core.exact_replay import ExpectedBlocks

__all__ = ["BoundStream", "LongReplayExact"]


class BoundStream:
    """`core.bound.bound_summary` (its exact case) of a ratio given block by block: the worst
    ratio and the first instant within BOUND_TOL of it. The first instant above a threshold
    is a strict running maximum, and the threshold only rises: only the running maxima within
    BOUND_TOL of the worst so far are kept (a handful)."""

    def __init__(self) -> None:
        self.worst = -np.inf
        self.records: list[tuple[int, float]] = []  # (instant, ratio), ratios increasing

    def add(self, k0: int, ratio: np.ndarray) -> None:
        r = np.asarray(ratio, dtype=float)
        ok = np.flatnonzero(np.isfinite(r))
        if not ok.size:
            return
        top = self.records[-1][1] if self.records else -np.inf
        # the block's strict running maxima above what came before
        run = np.maximum.accumulate(r[ok])
        rise = np.flatnonzero(np.diff(np.concatenate([[top], run])) > 0)
        self.records += [(k0 + int(ok[i]), float(run[i])) for i in rise]
        self.worst = max(self.worst, float(run[-1]))
        low = self.worst - BOUND_TOL * max(abs(self.worst), 1.0)
        self.records = [x for x in self.records if x[1] >= low]

    def summary(self) -> dict[str, Any] | None:
        if not self.records:
            return None
        worst = self.worst
        return {"holds": bool(worst <= 1.0 + BOUND_TOL), "worst": worst,
                "worst_step": self.records[0][0]}  # fmt: skip


class LongReplayExact:
    """Each architecture's exact values of the blocks of one recorded run (`window`, in
    order), `mask` (K+1, m) its shared measurement pattern (None: complete)."""

    def __init__(self, exact: ExpectedBlocks, mask: np.ndarray | None, m: int, block: int):
        self.exact, self.mask, self.m, self.block = exact, mask, m, block
        self.bounds: dict[str, BoundStream] = {a: BoundStream() for a in exact.blocks.archs}
        self.spool: Any = None

    def _present(self, k0: int, k1: int) -> np.ndarray:
        if self.mask is None:
            return np.ones((k1 - k0, self.m), dtype=bool)
        return self.mask[k0:k1]

    def prepare(self) -> None:
        """FBS's backward pass over the whole log, spooled (nothing without FBS)."""
        from fusionlog.driver.long_log import backward_spool

        if self.exact.smoother and self.spool is None:
            blocks = self.exact.blocks

            def readings(k0: int, k1: int) -> np.ndarray:
                return np.where(self._present(k0, k1), 0.0, np.nan)

            self.spool = backward_spool(blocks, readings, self.block)

    def window(self, k0: int, k1: int) -> dict[str, tuple[Any, np.ndarray]]:
        """{arch: (Expected (w, ...), the bound check's ratio (w,))} at the instants k0..k1-1."""
        self.prepare()
        out = {}
        for a, ex in self.exact.window(
            k0, k1, self._present(k0, k1), self._backward(k0, k1)
        ).items():
            ratio = np.asarray(ex.bound, dtype=float)
            self.bounds[a].add(k0, ratio)
            out[a] = (ex, ratio)
        if k1 >= self.exact.blocks.steps + 1:
            self.close()
        return out

    def _backward(self, k0: int, k1: int):
        """What `prepare` spooled of the instants k0..k1-1 (None without FBS)."""
        from fusionlog.driver.long_log import read_backward

        return read_backward(self.spool, k0, k1) if self.spool is not None else None

    def bound_summary(self, arch: str) -> dict[str, Any] | None:
        """summary.json's ``bound`` of the instants seen (`core.bound.bound_summary`)."""
        return self.bounds[arch].summary()

    def close(self) -> None:
        if self.spool is not None:
            self.spool.close()
            self.spool = None
