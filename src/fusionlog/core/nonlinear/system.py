"""A system with nonlinear sensors or motion (DESIGN.md, "Nonlinear sensors and motion"), as plain
immutable data: the motion model, the sensors' measurement models, the prior, the local filter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model import Prior
from ..timing import Schedule, schedule
from .local import UkfParams
from .measurement import Linear, Sensor, Stacked
from .motion import Motion

#: Values of `[estimate] filter`.
FILTERS: tuple[str, ...] = ("EKF", "UKF")


@dataclass(frozen=True)
class NonlinearSystem:
    """x_k = f(x_{k-1}, dt) + w,  z_k^(j) = h_j(x_k) + v^(j) with independent sensor noises.

    `filter` is the local filter of every architecture ("EKF" | "UKF"); `ukf` its parameters.
    `initial` is where the true x_0 is drawn from (default: the prior)."""

    motion: Motion
    sensors: tuple[Sensor, ...]
    prior: Prior
    filter: str
    dt: float
    state_names: tuple[str, ...]
    ukf: UkfParams = UkfParams()
    initial: Prior | None = None

    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return sum(s.dim for s in self.sensors)

    @property
    def linear(self) -> bool:
        """Linear motion and sensors: the EKF and the UKF are then the KF."""
        return self.motion.linear and all(isinstance(s, Linear) for s in self.sensors)

    @property
    def ukf_params(self) -> UkfParams | None:
        """The UKF's parameters, None for the EKF (how the local filter functions choose)."""
        return self.ukf if self.filter == "UKF" else None

    @property
    def stacked(self) -> Stacked:
        return Stacked(self.sensors)

    @property
    def sensor_slices(self) -> tuple[slice, ...]:
        return self.stacked.slices

    @property
    def truth_initial(self) -> Prior:
        return self.initial if self.initial is not None else self.prior

    def schedule(self, steps: int) -> Schedule:
        return schedule(self.dt, steps, tuple(s.timing for s in self.sensors))

    def sensor_index(self, name: str) -> int:
        return [s.name for s in self.sensors].index(name)


def intervals(times: np.ndarray) -> np.ndarray:
    """The intervals dt_k = t_k - t_{k-1}, one per instant after the first."""
    return np.diff(np.asarray(times, dtype=float))
