"""The identity kind's "System": classes, prior and sensors with confusion matrices (seed 004).

Challa & Koks's aircraft example (``shared/seeds/004_e832512ceaf07c5b.txt``): which class is
it, from sensors that each report a class, a named set of classes ("fast" = {Learjet, Falcon})
or "unknown" (the whole frame)? A sensor is described twice over, once per fusion rule:

* for Bayes (eqs. 36-37) by its confusion matrix, P(report | class), whose columns are the
  likelihoods of its reports (:meth:`IdentitySensor.likelihood`);
* for Dempster-Shafer (eqs. 43-47) by its reliability r: report R is the simple support
  function m(R) = r, m(frame) = 1 - r (:meth:`IdentitySensor.mass_table`).

Plain immutable data, no I/O: the scenario parser builds it, simulation and fusion read it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "ARCHITECTURES",
    "MAX_CLASSES",
    "SUM_TOL",
    "UNKNOWN",
    "IdentitySensor",
    "IdentitySystem",
]

#: Identity architectures (DESIGN.md): Bayes' rule and Dempster's rule.
ARCHITECTURES: tuple[str, ...] = ("BAYES", "DS")
#: The implicit name of the whole frame.
UNKNOWN = "unknown"
#: Largest frame: DS keeps 2^N masses per run.
MAX_CLASSES = 12
#: Tolerance of "sums to one" (prior, rows of the confusion matrices).
SUM_TOL = 1e-9


@dataclass(frozen=True, eq=False)
class IdentitySensor:
    """A sensor's report alphabet, its confusion matrix and its DS reliability."""

    name: str
    reports: tuple[str, ...]  # as written: class names, set names or "unknown"
    subsets: tuple[int, ...]  # each report's subset of the frame as a bitmask (subset_index)
    confusion: np.ndarray  # (N classes, len(reports)): P(report | class), rows sum to one
    reliability: float  # DS: m(report) = reliability, m(frame) = 1 - reliability

    def mass_table(self, n_classes: int) -> np.ndarray:
        """(len(reports) + 1, 2^N): the DS mass function of each report; last row: no report."""
        size = 1 << n_classes
        table = np.zeros((len(self.reports) + 1, size))
        table[:, size - 1] = 1.0
        for j, b in enumerate(self.subsets):
            table[j, size - 1] -= self.reliability
            table[j, b] += self.reliability
        return table

    def likelihood(self) -> np.ndarray:
        """(len(reports) + 1, N): P(report | class) of each report; last row (no report): 1."""
        return np.vstack([self.confusion.T, np.ones(self.confusion.shape[0])])


@dataclass(frozen=True, eq=False)
class IdentitySystem:
    """The frame of discernment, the prior over it and the sensors: what simulation and fusion
    need of an identity scenario (its Monte Carlo settings live in the scenario).

    `prior` is both the distribution each run's true class is drawn from and the fusion node's
    prior for BAYES (DS starts from the vacuous mass m(frame) = 1). `sets` are the named subsets
    a sensor may report; "unknown" is always the whole frame.
    """

    classes: tuple[str, ...]
    prior: np.ndarray  # (N,)
    sets: dict[str, tuple[str, ...]]
    sensors: tuple[IdentitySensor, ...]

    def __post_init__(self) -> None:
        # Shapes only: the scenario parser reports bad values with the file and key.
        n = len(self.classes)
        if np.shape(self.prior) != (n,):
            raise ValueError(f"prior has shape {np.shape(self.prior)}, expected ({n},)")
        for s in self.sensors:
            if len(s.subsets) != len(s.reports) or s.confusion.shape != (n, len(s.reports)):
                raise ValueError(
                    f"sensor {s.name!r}: confusion {s.confusion.shape} and {len(s.subsets)} "
                    f"subsets do not match {n} classes x {len(s.reports)} reports"
                )

    @property
    def n(self) -> int:
        """Number of classes N."""
        return len(self.classes)

    def to_dict(self) -> dict[str, Any]:
        """The resolved definitions as plain data (metadata, provenance)."""
        return {
            "classes": list(self.classes),
            "prior": [float(p) for p in self.prior],
            "sets": {k: list(v) for k, v in self.sets.items()},
            "sensors": [
                {
                    "name": s.name,
                    "reports": list(s.reports),
                    "subsets": [
                        [c for j, c in enumerate(self.classes) if b >> j & 1] for b in s.subsets
                    ],
                    "confusion": s.confusion.tolist(),
                    "reliability": s.reliability,
                }
                for s in self.sensors
            ],
        }
