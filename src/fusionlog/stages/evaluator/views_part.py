"""What the recording draws of single runs: the first runs' truth and estimates with their ±σ
(`SamplesPart`), and the state plane of a 2-D state (`PlanePart`: the first block's estimates,
the truth of its first run, and each input's and architecture's confidence ellipse)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fusionlog.driver import PlanCache

from .parts import Block, Finished, Part

__all__ = ["PLANE_POINTS", "PlanePart", "SamplesPart"]

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
        from fusionlog.core.metrics import chi2_quantile  # scipy: an evaluation's only

        inputs = {
            f"input {s.name}": self.plans.plan(f"SKF:{s.name}").reported_cov
            for s in self.plans.system.sensors
        }
        into.fields["plane"] = {
            "truth": self.truth,
            "estimates": self.points,
            "ellipses": {**inputs, **self.cov},
            # the ellipse of a 2-D Gaussian at the confidence: chi-square with 2 dof
            "scale": float(np.sqrt(chi2_quantile(self.confidence, 2))),
        }
