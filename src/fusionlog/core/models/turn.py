"""The coordinated-turn motion model (DESIGN.md, "Nonlinear sensors and motion").

The nearly coordinated turn on the state [x, vx, y, vy, omega] (Bar-Shalom, Li, Kirubarajan,
"Estimation with Applications to Tracking and Navigation", Sec. 11.7): with theta = omega dt,
a = sin(theta)/omega, b = (1 - cos theta)/omega,

    x' = x + a vx - b vy,   vx' = cos(theta) vx - sin(theta) vy,
    y' = y + b vx + a vy,   vy' = sin(theta) vx + cos(theta) vy,   omega' = omega,

which tends to constant velocity (a -> dt, b -> 0) as omega -> 0; Q(dt) is q_x, q_y times the
white-acceleration block [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis and q_turn dt for omega.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import NumericalError
from .base import MotionModel, register_motion

#: |omega dt| below which a, b and their omega-derivatives come from their Taylor series: there
#: the closed forms lose ~eps/theta^2 to cancellation, each series' first omitted term is at
#: most ~theta^6/2880 of its leading one (< 1e-15 at the threshold; da's needs its theta^5
#: term for that: without it, 3.6e-11).
SMALL_TURN = 1e-2
#: |omega dt| from which the turn is refused: from 2^52 rad on, consecutive doubles are a
#: radian or more apart, so the heading after one step (cos, sin of theta) is rounding, not
#: the turn rate. Below it theta^2, omega^2 and the series stay far inside the float range
#: (dt >= 1 ns), so no numpy overflow warning can arise either (omega = 1e300 gave five).
MAX_TURN = 2.0**52


def cv_block(dt: float) -> np.ndarray:
    """The white-acceleration noise of one axis [p, v] over dt, per unit spectral density."""
    return np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


def _turn_terms(omega: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
    """a, b, da/domega, db/domega, cos, sin of the coordinated turn over dt, elementwise."""
    with np.errstate(over="ignore"):  # an overflow to inf is refused just below
        th = omega * dt
    far = np.abs(th) >= MAX_TURN  # False for NaN (a run without an estimate)
    if far.any():
        w = float(np.asarray(omega)[far].flat[0])  # a Python float: w * dt is inf, no warning
        raise NumericalError(
            f"the coordinated turn overflows: turn rate omega = {w:.6g} rad/s over "
            f"{dt:.6g} s turns by {w * dt:.6g} rad, "
            "at or beyond 2^52 rad, where doubles are a radian apart (the heading is rounding)"
        )
    c, s = np.cos(th), np.sin(th)
    small = np.abs(th) < SMALL_TURN
    safe = np.where(small, 1.0, omega)  # the closed forms only where omega is not tiny
    t2 = th * th
    a = np.where(small, dt * (1 - t2 / 6 + t2 * t2 / 120), s / safe)
    b = np.where(small, dt * th * (0.5 - t2 / 24 + t2 * t2 / 720), (1 - c) / safe)
    da = np.where(
        small, dt * dt * th * (-1 / 3 + t2 / 30 - t2 * t2 / 840), (th * c - s) / (safe * safe)
    )
    db = np.where(
        small, dt * dt * (0.5 - t2 / 8 + t2 * t2 / 144), (th * s - (1 - c)) / (safe * safe)
    )
    return a, b, da, db, c, s


@register_motion
@dataclass(frozen=True)
class CoordinatedTurn(MotionModel):
    """The coordinated turn on [x, vx, y, vy, omega] (module docstring)."""

    kind = "coordinated-turn"

    q: tuple[float, float]  # white-acceleration spectral densities along x and y
    q_turn: float  # of the turn rate

    @property
    def n(self) -> int:
        return 5

    def f(self, x: np.ndarray, dt: float) -> np.ndarray:
        px, vx, py, vy, om = np.moveaxis(x, -1, 0)
        a, b, _, _, c, s = _turn_terms(om, dt)
        return np.stack(
            [px + a * vx - b * vy, c * vx - s * vy, py + b * vx + a * vy, s * vx + c * vy, om],
            axis=-1,
        )

    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        """df/dx: the rows above differentiated, d cos(theta)/domega = -dt sin(theta) etc."""
        _, vx, _, vy, om = np.moveaxis(x, -1, 0)
        a, b, da, db, c, s = _turn_terms(om, dt)
        J = np.zeros(x.shape + (5,))
        J[..., 0, 0] = J[..., 2, 2] = J[..., 4, 4] = 1.0
        J[..., 0, 1], J[..., 0, 3], J[..., 0, 4] = a, -b, da * vx - db * vy
        J[..., 1, 1], J[..., 1, 3], J[..., 1, 4] = c, -s, -dt * (s * vx + c * vy)
        J[..., 2, 1], J[..., 2, 3], J[..., 2, 4] = b, a, db * vx + da * vy
        J[..., 3, 1], J[..., 3, 3], J[..., 3, 4] = s, c, dt * (c * vx - s * vy)
        return J

    def Q(self, dt: float) -> np.ndarray:
        Q = np.zeros((5, 5))
        Q[0:2, 0:2] = self.q[0] * cv_block(dt)
        Q[2:4, 2:4] = self.q[1] * cv_block(dt)
        Q[4, 4] = self.q_turn * dt
        return Q
