"""Measurement models z = h(x) + v of the nonlinear sensors (DESIGN.md, "Nonlinear sensors and
motion"), evaluated for many states at once.

A model gives h(x) for x of shape (..., n), its analytic Jacobian dh/dx (..., m, n), R and which of
its components are angles (wrapped to (-pi, pi] wherever a difference of two of them is taken).
`Linear` is z = H x + v as a model of the same shape, so the filters treat every sensor alike.
The range-bearing family measures the target's planar position (the states `idx`) from the
sensor's place p:  range = sqrt(dx^2 + dy^2),  bearing = atan2(dy, dx),  d = (x_idx - p).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..timing import SensorTiming

#: The sensor kinds of `[[sensors]] kind` besides "linear", and the components each measures.
POLAR_KINDS: dict[str, tuple[str, ...]] = {
    "range-bearing": ("range", "bearing"),
    "range": ("range",),
    "bearing": ("bearing",),
}


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]: pi - ((pi - a) mod 2 pi), so -pi itself maps to pi."""
    return math.pi - np.mod(math.pi - a, 2.0 * math.pi)


def wrap_angles(d: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Differences d (..., m) with the components marked in `angles` (m,) wrapped."""
    if not angles.any():
        return d
    out = np.array(d, dtype=float, copy=True)
    out[..., angles] = wrap(out[..., angles])
    return out


@dataclass(frozen=True)
class Linear:
    """z = H x + v: a linear sensor as a measurement model (its Jacobian is H everywhere)."""

    name: str
    H: np.ndarray  # (m, n)
    R: np.ndarray  # (m, m)
    timing: SensorTiming = SensorTiming()
    kind: str = "linear"

    @property
    def dim(self) -> int:
        return self.H.shape[0]

    @property
    def angles(self) -> np.ndarray:
        return np.zeros(self.dim, dtype=bool)

    def h(self, x: np.ndarray) -> np.ndarray:
        return x @ self.H.T

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.H, x.shape[:-1] + self.H.shape)

    def ranges(self, x: np.ndarray) -> np.ndarray | None:
        """Distances to the sensor, where they matter (None: nowhere)."""
        return None


@dataclass(frozen=True)
class Polar:
    """A range-bearing, range or bearing sensor at `position`, measuring the states `idx`."""

    name: str
    kind: str  # one of POLAR_KINDS
    position: np.ndarray  # (2,)
    idx: tuple[int, int]  # the target's x and y in the state
    n: int
    R: np.ndarray  # (m, m) in m^2 and rad^2
    timing: SensorTiming = SensorTiming()
    components: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "components", POLAR_KINDS[self.kind])

    @property
    def dim(self) -> int:
        return len(self.components)

    @property
    def angles(self) -> np.ndarray:
        return np.array([c == "bearing" for c in self.components])

    def _delta(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x[..., self.idx[0]] - self.position[0], x[..., self.idx[1]] - self.position[1]

    def ranges(self, x: np.ndarray) -> np.ndarray:
        dx, dy = self._delta(x)
        return np.hypot(dx, dy)

    def h(self, x: np.ndarray) -> np.ndarray:
        dx, dy = self._delta(x)
        parts = {"range": lambda: np.hypot(dx, dy), "bearing": lambda: wrap(np.arctan2(dy, dx))}
        return np.stack([parts[c]() for c in self.components], axis=-1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """d range/d(x, y) = (dx, dy)/r;  d bearing/d(x, y) = (-dy, dx)/r^2; zero elsewhere.
        Undefined at r = 0 (the callers refuse a state on the sensor, `ranges`)."""
        dx, dy = self._delta(x)
        r2 = dx * dx + dy * dy
        r = np.sqrt(r2)
        J = np.zeros(x.shape[:-1] + (self.dim, self.n))
        ix, iy = self.idx
        with np.errstate(divide="ignore", invalid="ignore"):
            for row, c in enumerate(self.components):
                if c == "range":
                    J[..., row, ix], J[..., row, iy] = dx / r, dy / r
                else:
                    J[..., row, ix], J[..., row, iy] = -dy / r2, dx / r2
        return J


Sensor = Linear | Polar


@dataclass(frozen=True)
class Stacked:
    """Several sensors as one measurement z = [h_1(x); ...; h_S(x)] (eq. 30 for the CKF's one
    update per instant with every sensor that measures then); R block-diagonal."""

    sensors: tuple[Sensor, ...]

    @property
    def slices(self) -> tuple[slice, ...]:
        out, start = [], 0
        for s in self.sensors:
            out.append(slice(start, start + s.dim))
            start += s.dim
        return tuple(out)

    @property
    def dim(self) -> int:
        return sum(s.dim for s in self.sensors)

    @property
    def angles(self) -> np.ndarray:
        return np.concatenate([s.angles for s in self.sensors])

    @property
    def R(self) -> np.ndarray:
        R = np.zeros((self.dim, self.dim))
        for s, sl in zip(self.sensors, self.slices, strict=True):
            R[sl, sl] = s.R
        return R

    def h(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([s.h(x) for s in self.sensors], axis=-1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([s.jacobian(x) for s in self.sensors], axis=-2)
