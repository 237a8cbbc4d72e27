"""The posterior Cramér-Rao bound of a nonlinear model beside the Monte Carlo values (Tichavský
et al. 1998, `core.nonlinear.PcrbAccumulator`): the truth and which sensors measured, block by
block; no exact analysis exists for such a model, so each architecture's `expected` is null."""

from __future__ import annotations

from typing import Any

import numpy as np

from fusionlog.core.model import System
from fusionlog.io.mcap.topics import sensor_topic

from .parts import Block, Elsewhere, Finished, Part

__all__ = ["PcrbPart"]


class PcrbPart(Part):
    """The bound of `system` (the truth's, nonlinear) on the instants `times` (K+1,)."""

    def __init__(self, system: System, times: np.ndarray) -> None:
        from fusionlog.core.nonlinear import PcrbAccumulator

        self.acc = PcrbAccumulator(system, times)
        self.topics = [sensor_topic(s.name) for s in system.sensors]
        self._bound: np.ndarray | None = None
        self.complete = True  # every block came with its readings

    def add(self, block: Block) -> None:
        if block.has_truth:
            self.add_readings(block.truth, block.sensors)

    def merge(self, other: Elsewhere) -> None:
        if other.readings is not None:
            self.add_readings(*other.readings)

    def add_readings(self, truth: np.ndarray, sensors: dict[str, np.ndarray] | None) -> None:
        """Runs' truth (runs, K+1, n) and readings {topic: (runs, K+1, dim)} (NaN: absent)."""
        if sensors is None or any(t not in sensors for t in self.topics):
            self.complete = False
            return
        present = np.stack([~np.isnan(sensors[t]).any(axis=-1) for t in self.topics], axis=-1)
        self.acc.add(truth, present)

    @property
    def bound(self) -> np.ndarray | None:
        """J_k^-1 (K+1, n, n), None when some block lacked its readings."""
        if self._bound is None and self.complete and self.acc.runs:
            self._bound = self.acc.bound()
        return self._bound

    def summary(self) -> dict[str, Any] | None:
        """summary.json's "pcrb" (None: some block lacked its readings)."""
        from fusionlog.core.nonlinear import pcrb_summary

        return None if self.bound is None else pcrb_summary(self.bound)

    def summarise(self, into: Finished) -> None:
        for a, entry in into.archs.items():
            if a in into.metric_runs:  # an entry with truth metrics: no exact values
                entry["expected"] = None
        into.summary["pcrb"] = self.summary()
        b = self.bound
        into.fields["pcrb"] = None if b is None else np.diagonal(b, axis1=-2, axis2=-1).copy()
