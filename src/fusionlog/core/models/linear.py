"""The linear kinds: z = H x + v (eq. 13) and x_{k+1} = F x_k + G w_k (eq. 12).

Their matrices are what the compiled plans and the exact analysis work with (gains that do
not depend on the data); ``h``, ``f`` and the Jacobians are there so that any filter can ask a
linear model what it asks a nonlinear one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..timing import SensorTiming
from .base import MotionModel, SensorModel, register_motion, register_sensor

__all__ = ["LinearMotion", "LinearSensor"]


@register_sensor
@dataclass(frozen=True)
class LinearSensor(SensorModel):
    """One sensor of eq. (13): z = H x + v, v ~ N(0, R), measuring when `timing` says."""

    kind = "linear"
    linear = True

    name: str
    H: np.ndarray  # (m, n)
    R: np.ndarray  # (m, m)
    timing: SensorTiming = SensorTiming()

    @property
    def dim(self) -> int:
        return self.H.shape[0]

    def h(self, x: np.ndarray) -> np.ndarray:
        """H x for states x (..., n): (..., m)."""
        return x @ self.H.T

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """H, broadcast to x's leading axes: (..., m, n)."""
        x = np.asarray(x)
        return np.broadcast_to(self.H, x.shape[:-1] + self.H.shape)


@register_motion
@dataclass(frozen=True)
class LinearMotion(MotionModel):
    """x_{k+1} = F x_k + w, w ~ N(0, Q) over the model's dt (Q in state space: G Q G^T).

    With a continuous-time model (A, Qc) (the constant-velocity and continuous kinds), other
    intervals are discretised by Van Loan's method (`core.timing.van_loan`): F = expm(A dt);
    without one, only dt itself has a transition.
    """

    kind = "linear"
    linear = True

    F_dt: np.ndarray  # (n, n), over dt
    Q_dt: np.ndarray  # (n, n), over dt
    dt: float = 1.0
    continuous: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def n(self) -> int:
        return self.F_dt.shape[0]

    def _discrete(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        if dt == self.dt:
            return self.F_dt, self.Q_dt
        if self.continuous is None:
            raise ValueError(
                f"a model given by F and Q has no transition over {dt} s (only over dt = "
                f"{self.dt} s): give it in continuous time"
            )
        from ..timing import van_loan

        Fs, Qs = van_loan(*self.continuous, np.array([dt]))
        return Fs[0], Qs[0]

    def F(self, dt: float) -> np.ndarray:
        """The transition matrix over dt: (n, n)."""
        return self._discrete(dt)[0]

    def Q(self, dt: float) -> np.ndarray:
        """The process noise covariance over dt: (n, n)."""
        return self._discrete(dt)[1]

    def f(self, x: np.ndarray, dt: float) -> np.ndarray:
        """F x for states x (..., n): (..., n)."""
        return x @ self.F(dt).T

    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        """F, broadcast to x's leading axes: (..., n, n)."""
        F = self.F(dt)
        return np.broadcast_to(F, np.shape(x)[:-1] + F.shape)
