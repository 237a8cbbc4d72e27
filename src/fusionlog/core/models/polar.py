"""The range-bearing family of sensor models (DESIGN.md, "Nonlinear sensors and motion").

A sensor at `position` p measures the target's planar position (the states `idx`, its x and y):

    range = sqrt(dx^2 + dy^2),  bearing = atan2(dy, dx) wrapped to (-pi, pi],  (dx, dy) = x_idx - p

with analytic Jacobians  d range/d(x, y) = (dx, dy)/r,  d bearing/d(x, y) = (-dy, dx)/r^2. The
bearing components are angles: wherever two measurements are subtracted (`residual`, what every
filter asks of a sensor model) the bearings' difference is wrapped (`wrap_angles`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..timing import SensorTiming
from .base import SensorModel, register_sensor

__all__ = [
    "POLAR_KINDS",
    "BearingSensor",
    "PolarSensor",
    "RangeBearingSensor",
    "RangeSensor",
    "wrap",
    "wrap_angles",
]


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]: pi - ((pi - a) mod 2 pi), so -pi itself maps to pi.

    t mod 2 pi is t itself (exactly: fmod is exact) for t in [0, 2 pi), which is where an
    angle already in (-pi, pi] puts t = pi - a: np.mod, ~7x slower than a subtraction, runs
    only on the other entries; the numbers are np.mod's to the last bit either way, except
    where np.mod rounds a tiny negative t up to 2 pi itself (an angle an ulp or so above pi):
    that would give -pi, the excluded end, and gives pi."""
    t = np.subtract(math.pi, a)
    if np.ndim(t) == 0:
        m = np.mod(t, 2.0 * math.pi)
        return math.pi - (m if m < 2.0 * math.pi else 0.0)
    # a few angles (one run's): Python's comparisons cost less than numpy's three passes
    if t.size <= _FEW and all(0.0 <= v < _TWO_PI for v in t.ravel().tolist()):
        return np.subtract(math.pi, t, out=t)
    out = (t < 0.0) | (t >= 2.0 * math.pi)
    if out.any():
        m = np.mod(t[out], 2.0 * math.pi)
        m[m >= 2.0 * math.pi] = 0.0
        t[out] = m
    np.subtract(math.pi, t, out=t)
    return t


_TWO_PI = 2.0 * math.pi
#: Arrays of at most this many angles are tested for being in range in Python (`wrap`).
_FEW = 16


def wrap_angles(d: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Differences d (..., m) with the components marked in `angles` (m,) wrapped."""
    if not angles.any():
        return d
    out = np.array(d, dtype=float, copy=True)
    out[..., angles] = wrap(out[..., angles])
    return out


@dataclass(frozen=True)
class PolarSensor(SensorModel):
    """A sensor at `position` measuring range and/or bearing of the states `idx` (x, y)."""

    #: what it measures, in order
    components: ClassVar[tuple[str, ...]] = ()

    name: str
    position: np.ndarray  # (2,)
    idx: tuple[int, int]  # the target's x and y in the state
    n: int
    R: np.ndarray  # (m, m), in m^2 and rad^2
    timing: SensorTiming = SensorTiming()
    position_states: tuple[str, str] = ("x", "y")  # the names of the states `idx`

    @property
    def dim(self) -> int:
        return len(self.components)

    @property
    def angles(self) -> np.ndarray:
        return np.array([c == "bearing" for c in self.components])

    @property
    def _bearing(self) -> int | None:
        """The bearing's component, if it measures one."""
        return self.components.index("bearing") if "bearing" in self.components else None

    def _delta(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x[..., self.idx[0]] - self.position[0], x[..., self.idx[1]] - self.position[1]

    def ranges(self, x: np.ndarray) -> np.ndarray:
        """The distances from the sensor to states x (...,) as the Jacobian has them (the r of
        `linearised`): 0 where it is undefined, also where dx^2 + dy^2 underflows."""
        dx, dy = self._delta(x)
        return np.sqrt(dx * dx + dy * dy)

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """z - z_hat with the bearing wrapped to (-pi, pi] (`wrap_angles`'s numbers, on the
        bearing's column alone)."""
        d = np.subtract(z, z_hat, dtype=float)
        if (i := self._bearing) is not None:
            d[..., i] = wrap(d[..., i])
        return d

    def h(self, x: np.ndarray) -> np.ndarray:
        dx, dy = self._delta(x)
        parts = {"range": lambda: np.hypot(dx, dy), "bearing": lambda: wrap(np.arctan2(dy, dx))}
        return np.stack([parts[c]() for c in self.components], axis=-1)

    def linearised(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
        """`h` and `jacobian` on lanes (`SensorModel.linearised`) from one (dx, dy): only the
        columns of x and y, the others are zero. The range is the r the Jacobian divides by,
        sqrt(dx^2 + dy^2) (`h`'s hypot differs in the last bit at most, at 7x the cost)."""
        dx, dy = self._delta(x)
        r2 = dx * dx + dy * dy
        r = np.sqrt(r2)
        M = dx.shape[0]
        h, J = np.empty((self.dim, M)), np.empty((self.dim, 2, M))
        with np.errstate(divide="ignore", invalid="ignore"):
            for row, c in enumerate(self.components):
                if c == "range":
                    h[row] = r
                    np.divide(dx, r, out=J[row, 0])
                    np.divide(dy, r, out=J[row, 1])
                else:
                    h[row] = wrap(np.arctan2(dy, dx))
                    np.divide(-dy, r2, out=J[row, 0])
                    np.divide(dx, r2, out=J[row, 1])
        return h, J, self.idx

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """The module docstring's derivatives; undefined at r = 0 (the filters refuse a state
        on the sensor, naming the run and the instant)."""
        dx, dy = self._delta(x)
        r2 = dx * dx + dy * dy
        r = np.sqrt(r2)
        J = np.zeros(np.shape(x)[:-1] + (self.dim, self.n))
        ix, iy = self.idx
        with np.errstate(divide="ignore", invalid="ignore"):
            for row, c in enumerate(self.components):
                if c == "range":
                    J[..., row, ix], J[..., row, iy] = dx / r, dy / r
                else:
                    J[..., row, ix], J[..., row, iy] = -dy / r2, dx / r2
        return J


@register_sensor
@dataclass(frozen=True)
class RangeBearingSensor(PolarSensor):
    """Measures [range, bearing] (a radar)."""

    kind = "range-bearing"
    components = ("range", "bearing")


@register_sensor
@dataclass(frozen=True)
class RangeSensor(PolarSensor):
    """Measures the range alone."""

    kind = "range"
    components = ("range",)


@register_sensor
@dataclass(frozen=True)
class BearingSensor(PolarSensor):
    """Measures the bearing alone (a camera, a direction finder)."""

    kind = "bearing"
    components = ("bearing",)


#: kind -> model class of the family
POLAR_KINDS: dict[str, type[PolarSensor]] = {
    c.kind: c for c in (RangeBearingSensor, RangeSensor, BearingSensor)
}
