"""The evaluator's part of the trajectory metrics (DESIGN.md "Trajectory metrics"): APE and
RPE of each architecture after the scenario's alignment, for replays and simulations alike; each
block's runs measured by `..trajectory_eval.trajectory_block`, the sums merged in block order
(a Dask worker's through `Elsewhere.trajectory`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fusionlog.core.trajectory import TrajectorySums

from ..trajectory_eval import trajectory_block
from .parts import Block, Elsewhere, Finished, Part

__all__ = ["TrajectoryPart"]


class TrajectoryPart(Part):
    """APE/RPE sums per architecture over the blocks of an evaluation (an evaluator part)."""

    def __init__(self, sc: Any, archs: Sequence[str], times: np.ndarray, source: str) -> None:
        self.sc, self.times, self.source = sc, np.asarray(times, dtype=float), source
        self.archs = list(archs)
        self.sums: dict[str, TrajectorySums] = {}
        self.spread: np.ndarray | None = None  # run 0's truth: variance of each position

    @classmethod
    def of(
        cls, sc: Any, archs: Sequence[str], times: np.ndarray, has_truth: bool, source: str
    ) -> TrajectoryPart | None:
        """The part, or None when there is nothing to measure (no position states, no truth)."""
        if sc.trajectory is None or not has_truth:
            return None
        return cls(sc, archs, times, source)

    def add(self, block: Block) -> None:
        if not block.has_truth:
            return
        off, truth = block.off, block.truth
        means = {a: e[0] for a, e in block.estimates.items()}
        sums = trajectory_block(self.sc, self.times, truth, means, off, self.source)
        self._merge(sums or {})
        if off == 0 and truth.shape[0]:
            g = truth[0][:, list(self.sc.trajectory.positions)]
            g = g[np.isfinite(g).all(axis=1)]
            self.spread = g.var(axis=0) if len(g) else None

    def merge(self, other: Elsewhere) -> None:
        self._merge(other.trajectory)

    def summarise(self, into: Finished) -> None:
        for a, entry in into.archs.items():
            if "mse" in entry:
                entry |= self.summary(a)
        into.fields["trajectory"] = self.recording()

    def _merge(self, sums: dict[str, TrajectorySums]) -> None:
        for a, s in sums.items():
            self.sums[a] = self.sums[a].merge(s) if a in self.sums else s

    def summary(self, arch: str) -> dict[str, Any]:
        """{"ape": ..., "rpe": ...} of summary.json (empty where no run was measured)."""
        s = self.sums.get(arch)
        if s is None:
            return {}
        ape, rpe = s.summary()
        return {"ape": ape, "rpe": rpe}

    def recording(self) -> dict[str, Any] | None:
        """What the recording draws (`io.rrd.trajectory`): the position states' names and
        indices, each architecture's APE and RPE over time and run 0's aligned positions
        (K+1, m)."""
        if not self.sums:
            return None
        pos = list(self.sc.trajectory.positions)
        names = [self.sc.state_names[i] for i in pos]
        out: dict[str, Any] = {"states": names, "positions": pos, "series": {}, "aligned": {}}
        if self.spread is not None:  # run 0's truth: the recording's plane of the paths
            out["spread"] = self.spread
        for a in self.archs:
            s = self.sums.get(a)
            if s is None:
                continue
            out["series"][a] = s.series()
            if s.first is not None:
                out["aligned"][a] = s.first.aligned
        return out
