"""What the evaluation checks without ground truth, from the sensor readings, only where they
say something: each architecture's NIS (`stages.consistency.NisAccumulator`; a replayed
recording), each sensor's availability (sensors with their own timing, or a replay), and the
first run's readings of a state drawn under its estimates."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fusionlog.core.model import System

from ..consistency import NisAccumulator, availability
from .parts import Block, Finished, Part

__all__ = ["NisPart"]


class NisPart(Part):
    """`scheduled` {sensor: (K+1,) bool or its `StepMask` (`[k0:k1]`: a bool array)}, each
    sensor's scheduled instants; `recorded`: a replay (NIS of the architectures `known`, and the
    first run's normalised innovations)."""

    def __init__(
        self,
        system: System,
        known: Sequence[str],
        instants: int,
        runs: int,
        scheduled: dict[str, np.ndarray],
        recorded: bool,
        sensor_topics: Sequence[str],
        confidence: float,
    ) -> None:
        self.system, self.M, self.scheduled = system, runs, scheduled
        self.topics, self.confidence, self.recorded = list(sensor_topics), confidence, recorded
        self.known, self.instants = list(known), instants
        # (K+1) sums per architecture and sensor, made when the first block comes (a long log
        # evaluated in blocks of time never makes them: `StateEvaluator.time_windows`)
        self.nis: NisAccumulator | None = None
        self.measured: dict[str, np.ndarray] = {}
        self.measured_points: dict[int, dict[str, np.ndarray]] = {}

    @property
    def archs(self) -> list[str]:
        """The architectures whose NIS is computed (a replay's)."""
        return self.known if self.recorded else []

    def _sums(self) -> None:
        if not self.measured:
            self.measured = {s.name: np.zeros(self.instants) for s in self.system.sensors}
            if self.recorded:
                self.nis = NisAccumulator(self.system, self.known, self.instants)

    def add(self, block: Block) -> None:
        sensors = block.sensors
        if sensors is None:
            return
        self._sums()
        fs = self.system
        if self.nis is not None:
            z = np.concatenate([sensors[t] for t in self.topics], axis=-1)
            self.nis.add(z, {a: block.estimates[a] for a in self.nis.archs})
            if not self.measured_points:  # the first run's readings of a state, under its estimates
                H = fs.linear_measurement() if fs.linear else None
                for s, t, sl in zip(fs.sensors, self.topics, fs.sensor_slices, strict=True):
                    for row, h in enumerate(H[sl] if H is not None else ()):
                        if np.count_nonzero(h) == 1 and h.max() == 1.0:
                            state = int(np.argmax(h))
                            self.measured_points.setdefault(state, {})[s.name] = sensors[t][
                                0, :, row
                            ]
        for s, t in zip(fs.sensors, self.topics, strict=True):
            self.measured[s.name] += (~np.isnan(sensors[t]).any(axis=-1)).sum(axis=0)

    def summarise(self, into: Finished) -> None:
        self._sums()
        if self.nis is not None:
            for a, entry in self.nis.summary(self.confidence).items():
                if a in into.archs:
                    into.archs[a]["nis"] = entry
        into.fields["availability"] = {
            name: availability(self.measured[name], self.scheduled[name][:], self.M)
            for name in self.measured
        }
        into.fields["measured"] = self.measured_points
        into.fields["nis"] = self.nis.series(self.confidence) if self.nis is not None else None
        into.fields["innovations"] = self.nis.first_run() if self.nis is not None else None
