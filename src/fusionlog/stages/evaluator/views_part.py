"""What the recording draws of single runs: the first runs' truth and estimates with their ±σ
(`SamplesPart`), and the state plane of a 2-D state (`PlanePart`: the first block's estimates,
the truth of its first run, and each input's and architecture's confidence ellipse)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fusionlog.driver import PlanCache

from .parts import Block, Finished, Part

__all__ = ["PLANE_POINTS", "LongPlane", "PlanePart", "SamplesPart"]

#: Sample estimates per architecture drawn in the state-plane view.
PLANE_POINTS = 300


class SamplesPart(Part):
    """The runs 0..`count`-1: truth (K+1, n) and {arch: (mean, std)} each."""

    def __init__(self, archs: Sequence[str], count: int) -> None:
        self.archs, self.count = list(archs), count
        self.samples: dict[int, Any] = {}

    def add(self, block: Block) -> None:
        x, off = block.truth, block.off
        for a in self.archs:
            mean, cov = block.estimates[a]
            for r in range(off, min(off + x.shape[0], self.count)):
                c = cov if cov.ndim == 3 else cov[r - off]
                std = np.sqrt(np.clip(np.diagonal(c, axis1=-2, axis2=-1), 0, None))
                self.samples.setdefault(r, (x[r - off], {}))[1][a] = (mean[r - off], std)

    def summarise(self, into: Finished) -> None:
        into.fields["samples"] = self.samples


class PlanePart(Part):
    """The plane view of the first block (`plans`: the filter's, for each sensor's own
    estimate's covariance, the "input" ellipses)."""

    def __init__(self, archs: Sequence[str], plans: PlanCache, confidence: float) -> None:
        self.archs, self.plans, self.confidence = list(archs), plans, confidence
        self.points: dict[str, np.ndarray] = {}
        self.truth: np.ndarray | None = None
        self.cov: dict[str, np.ndarray] = {}

    def add(self, block: Block) -> None:
        if block.off != 0:
            return
        self.truth = block.truth[0]
        for a in self.archs:
            mean, cov = block.estimates[a]
            self.points[a] = np.moveaxis(mean[:PLANE_POINTS], 0, 1)  # (K+1, P, 2)
            self.cov[a] = cov if cov.ndim == 3 else cov[0]

    def summarise(self, into: Finished) -> None:
        if self.truth is None:
            return
        inputs = {
            f"input {s.name}": self.plans.plan(f"SKF:{s.name}").reported_cov
            for s in self.plans.system.sensors
        }
        into.fields["plane"] = {
            "truth": self.truth,
            "estimates": self.points,
            "ellipses": {**inputs, **self.cov},
            "scale": _scale(self.confidence),
        }


def _scale(confidence: float) -> float:
    """The ellipse of a 2-D Gaussian at the confidence: chi-square with 2 dof."""
    from fusionlog.core.metrics import chi2_quantile  # scipy: an evaluation's only

    return float(np.sqrt(chi2_quantile(confidence, 2)))


class LongPlane:
    """`PlanePart`'s view of a long one-run log block by block (issue 34), in memory that does
    not grow with its instants: its frames at the recording's points' instants `steps` only
    (`core.decimate.plane_at`: each a real state and covariance), the inputs' ellipses from
    the short plans of each sensor's SKF (`inputs`, a `SteadyLog`)."""

    def __init__(self, part: PlanePart, inputs: Any, steps: np.ndarray) -> None:
        self.part, self.inputs, self.steps = part, inputs, steps
        self.frames: list[dict[str, Any]] = []

    def add(self, k0: int, k1: int, truth: np.ndarray, estimates: dict[str, Any]) -> None:
        """A block: truth (1, w, 2), {arch: (mean (1, w, 2), cov (w, 2, 2))}."""
        from fusionlog.core.decimate import plane_at

        at = self.steps[(self.steps >= k0) & (self.steps < k1)]
        if not len(at):
            return
        sensors = self.part.plans.system.sensors
        ellipses = {f"input {s.name}": self.inputs.cov(f"SKF:{s.name}", k0, k1) for s in sensors}
        points = {}
        for a in self.part.archs:
            mean, cov = estimates[a]
            points[a] = np.moveaxis(mean[:PLANE_POINTS], 0, 1)
            ellipses[a] = cov if cov.ndim == 3 else cov[0]
        plane = {"truth": truth[0], "estimates": points, "ellipses": ellipses}
        self.frames.append(plane_at(plane, at, k0))  # type: ignore[arg-type]

    def result(self) -> dict[str, Any] | None:
        """The `Evaluation`'s ``plane`` at the points' instants."""
        if not self.frames:
            return None
        f = self.frames

        def cat(key: str) -> dict[str, np.ndarray]:
            return {k: np.concatenate([x[key][k] for x in f]) for k in f[0][key]}

        return {
            "truth": np.concatenate([x["truth"] for x in f]),
            "estimates": cat("estimates"),
            "ellipses": cat("ellipses"),
            "scale": _scale(self.part.confidence),
        }
