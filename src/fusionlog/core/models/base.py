"""Model components: what a sensor and a motion model are to the estimators, and their registry.

A sensor model is z = h(x) + v, v ~ N(0, R) (eq. 13 when h is linear); a motion model is
x_{k+1} = f(x_k, dt) + w, w ~ N(0, Q(dt)) (eq. 12 when f is linear). The estimators ask these
objects, never a matrix attribute of a particular kind:

* ``h(x)`` / ``f(x, dt)`` on states (..., n), the value the local filter predicts;
* ``jacobian(x)`` / ``jacobian(x, dt)``, (..., m, n) / (..., n, n), the linearisation an
  extended filter uses (the same matrix everywhere for a linear kind);
* ``R`` / ``Q(dt)``, the noise covariances;
* ``residual(z, z_hat)``, the innovation (wrapped where a component is an angle).

A *linear* kind (``linear = True``) also exposes its matrix (``H`` of a sensor, ``F(dt)`` of a
motion): the compiled plans of `core.architectures` (gains that do not depend on the data) and
the exact analysis of `core.exact` exist only for those, and reach them through
``System.linear_measurement`` / ``System.F_at``, the one place that says so when a model is
not linear. A nonlinear kind is run by a filter that linearises (EKF) or samples (UKF).

The registries map a kind's name (the scenario's ``kind = "..."``) to its class: adding a
sensor kind is a new class and its ``@register_sensor``, plus its TOML syntax
(`fusionlog.scenario.sensors`), nothing in the architectures.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, TypeVar

import numpy as np

from ...errors import FusionlogError
from ..timing import SensorTiming

__all__ = [
    "MOTION_KINDS",
    "SENSOR_KINDS",
    "MotionModel",
    "NotLinear",
    "SensorModel",
    "register_motion",
    "register_sensor",
]


class NotLinear(FusionlogError, ValueError):
    """A linear-only computation (a compiled plan, the exact analysis) met a nonlinear model."""


class SensorModel(ABC):
    """z = h(x) + v, v ~ N(0, R), measuring when `timing` says.

    Subclasses are frozen dataclasses with at least ``name``, ``R`` (m, m) and ``timing``; a
    linear kind also has ``H`` (m, n), read only through `core.model.System.linear_measurement`
    (one place refuses a nonlinear sensor there).
    """

    #: the scenario's ``[[sensors]] kind``
    kind: ClassVar[str] = ""
    #: whether h is linear (then `H` is its matrix)
    linear: ClassVar[bool] = False

    name: str
    R: np.ndarray
    timing: SensorTiming

    @property
    def dim(self) -> int:
        """m, the length of a measurement."""
        return self.R.shape[0]

    @abstractmethod
    def h(self, x: np.ndarray) -> np.ndarray:
        """The noise-free measurement of states x (..., n): (..., m)."""

    @abstractmethod
    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """dh/dx at states x (..., n): (..., m, n)."""

    def linearised(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
        """h(x) and the Jacobian at states x (M, n) on lanes (`core.kernels`), as the EKF's
        update computes with them: (m, M), its columns `cols` (m, len(cols), M), and `cols`,
        the state columns where the Jacobian may be nonzero (all of them unless a kind knows
        better)."""
        J = self.jacobian(x)
        h = np.ascontiguousarray(self.h(x).T)
        return h, np.ascontiguousarray(J.transpose(1, 2, 0)), tuple(range(J.shape[-1]))

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """z - z_hat (..., m): the innovation a filter forms. A kind whose components are
        angles overrides it to wrap them to (-pi, pi] (a bearing's residual)."""
        return z - z_hat


class MotionModel(ABC):
    """x_{k+1} = f(x_k, dt) + w, w ~ N(0, Q(dt)) in state space (G Q G^T of eq. 12)."""

    kind: ClassVar[str] = ""
    linear: ClassVar[bool] = False

    @property
    @abstractmethod
    def n(self) -> int:
        """The state's length."""

    @abstractmethod
    def f(self, x: np.ndarray, dt: float) -> np.ndarray:
        """The states x (..., n) propagated over dt seconds, without noise: (..., n)."""

    @abstractmethod
    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        """df/dx at x (..., n) over dt: (..., n, n)."""

    @abstractmethod
    def Q(self, dt: float) -> np.ndarray:
        """The process noise covariance (state space) over dt: (n, n)."""

    def F(self, dt: float) -> np.ndarray:
        """The transition matrix (n, n) over dt of a linear motion model."""
        raise NotLinear(f"motion model {self.kind} is nonlinear: it has no matrix F")


#: kind name -> sensor model class
SENSOR_KINDS: dict[str, type[SensorModel]] = {}
#: kind name -> motion model class
MOTION_KINDS: dict[str, type[MotionModel]] = {}

S = TypeVar("S", bound=type[SensorModel])
MM = TypeVar("MM", bound=type[MotionModel])


def register_sensor(cls: S) -> S:
    """Class decorator: make a sensor kind known by its ``kind`` name."""
    if not cls.kind or cls.kind in SENSOR_KINDS:
        raise ValueError(f"sensor kind {cls.kind!r} is empty or registered twice")
    SENSOR_KINDS[cls.kind] = cls
    return cls


def register_motion(cls: MM) -> MM:
    """Class decorator: make a motion kind known by its ``kind`` name."""
    if not cls.kind or cls.kind in MOTION_KINDS:
        raise ValueError(f"motion kind {cls.kind!r} is empty or registered twice")
    MOTION_KINDS[cls.kind] = cls
    return cls
