"""Motion models x_k = f(x_{k-1}, dt) + w, w ~ N(0, Q(dt)), evaluated for many states at once.

`LinearMotion` is F x with the scenario's F, Q (and, for instants other than k dt, its continuous
model discretised by Van Loan's method). `CoordinatedTurn` is the nearly coordinated turn on the
state [x, vx, y, vy, omega] (Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking
and Navigation", Sec. 11.7): with theta = omega dt, a = sin(theta)/omega, b = (1 - cos theta)/omega,

    x' = x + a vx - b vy,   vx' = cos(theta) vx - sin(theta) vy,
    y' = y + b vx + a vy,   vy' = sin(theta) vx + cos(theta) vy,   omega' = omega,

which tends to constant velocity (a -> dt, b -> 0) as omega -> 0; Q(dt) is q_x, q_y times the
white-acceleration block [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis and q_turn dt for omega.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: |omega dt| below which a, b and their omega-derivatives come from their Taylor series: there
#: the closed forms lose ~eps/theta^2 to cancellation, the series' first omitted term is
#: ~theta^6/5040 of the leading one (< 1e-15 at the threshold).
SMALL_TURN = 1e-2


def cv_block(dt: float) -> np.ndarray:
    """The white-acceleration noise of one axis [p, v] over dt, per unit spectral density."""
    return np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


@dataclass(frozen=True)
class LinearMotion:
    """x_k = F x_{k-1} + w: F, Q at dt (Q in state space, G Q G^T), and the continuous model
    (A, Qc) when there is one, for intervals other than dt."""

    F: np.ndarray
    Q: np.ndarray
    dt: float
    continuous: tuple[np.ndarray, np.ndarray] | None = None
    _cache: dict = field(default_factory=dict, compare=False, repr=False)
    linear: bool = True

    def matrices(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """F and Q over an interval dt (the scenario's own at dt)."""
        # the log's times are whole nanoseconds: an interval within that of dt is dt
        if abs(dt - self.dt) <= 1e-9 or self.continuous is None:
            return self.F, self.Q
        key = round(dt, 9)
        if key not in self._cache:
            from ..timing import van_loan

            self._cache[key] = van_loan(*self.continuous, dt)
        return self._cache[key]

    def f(self, x: np.ndarray, dt: float) -> np.ndarray:
        return x @ self.matrices(dt)[0].T

    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        F = self.matrices(dt)[0]
        return np.broadcast_to(F, x.shape[:-1] + F.shape)

    def noise(self, dt: float) -> np.ndarray:
        return self.matrices(dt)[1]


def _turn_terms(omega: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
    """a, b, da/domega, db/domega, cos, sin of the coordinated turn over dt, elementwise."""
    th = omega * dt
    c, s = np.cos(th), np.sin(th)
    small = np.abs(th) < SMALL_TURN
    safe = np.where(small, 1.0, omega)  # the closed forms only where omega is not tiny
    t2 = th * th
    a = np.where(small, dt * (1 - t2 / 6 + t2 * t2 / 120), s / safe)
    b = np.where(small, dt * th * (0.5 - t2 / 24 + t2 * t2 / 720), (1 - c) / safe)
    da = np.where(small, dt * dt * th * (-1 / 3 + t2 / 30), (th * c - s) / (safe * safe))
    db = np.where(
        small, dt * dt * (0.5 - t2 / 8 + t2 * t2 / 144), (th * s - (1 - c)) / (safe * safe)
    )
    return a, b, da, db, c, s


@dataclass(frozen=True)
class CoordinatedTurn:
    """The coordinated turn on [x, vx, y, vy, omega] (module docstring)."""

    q: tuple[float, float]  # white-acceleration spectral densities along x and y
    q_turn: float  # of the turn rate
    linear: bool = False

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

    def noise(self, dt: float) -> np.ndarray:
        Q = np.zeros((5, 5))
        Q[0:2, 0:2] = self.q[0] * cv_block(dt)
        Q[2:4, 2:4] = self.q[1] * cv_block(dt)
        Q[4, 4] = self.q_turn * dt
        return Q


Motion = LinearMotion | CoordinatedTurn
