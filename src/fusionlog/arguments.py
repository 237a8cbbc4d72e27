"""What the Python API's arguments must be (`fusionlog.api`): each misuse is one
`ValidationError` (a `FusionlogError`) naming the argument as the API calls it
(``architectures``, ``sim.measurements['s1']``, ``estimates['CKF'].cov``) and the problem,
before numpy meets it deep inside a filter or the evaluator: the Python side of the CLI's
one-line errors (DESIGN.md "Python API").

Shapes are those the API documents: ``sim.times`` (K+1,), ``sim.truth`` (M, K+1, n),
``sim.measurements[sensor]`` (M, K+1, m), an estimate's ``mean`` (M, K+1, n) and ``cov``
(M, K+1, n, n). Values: floating point; NaN marks a missing reading or an undefined estimate
(both its mean and its covariance, as the filters leave them before a prior exists); an
infinite estimate, or a covariance that is not positive semidefinite, is refused rather than
left out of the metrics (`core.linalg.not_a_covariance`, the check the CLI's evaluate makes
of a negative variance).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .core.linalg import not_a_covariance
from .core.model import System
from .errors import ValidationError

__all__ = [
    "check_architecture_names",
    "check_estimate_shapes",
    "check_estimate_values",
    "check_simulation",
]


def _what(v: Any) -> str:
    """How a value is called in a message: its type, and its shape and dtype for an array."""
    if isinstance(v, np.ndarray):
        return f"an array of shape {v.shape} and dtype {v.dtype}"
    return f"{v!r} ({type(v).__name__})" if isinstance(v, int | float | str) else type(v).__name__


def _array(v: Any, where: str, shape: tuple[int | None, ...], dtype: str = "f") -> np.ndarray:
    """`v` as the documented array: a numpy array of `shape` (None: any size) whose dtype kind
    is in `dtype` ("f" floating point, "b" boolean); nested lists are refused by name."""
    if not isinstance(v, np.ndarray):
        raise ValidationError(
            f"{where}: expected a numpy array of shape {_shape(shape)}, got {_what(v)}"
        )
    if v.dtype.kind not in dtype:
        want = "floating-point values" if dtype == "f" else "booleans"
        kind = "complex values" if v.dtype.kind == "c" else f"dtype {v.dtype}"
        raise ValidationError(f"{where}: expected {want}, got {kind}")
    if v.ndim != len(shape) or any(s not in (None, h) for s, h in zip(shape, v.shape, strict=True)):
        raise ValidationError(f"{where}: expected shape {_shape(shape)}, got {v.shape}")
    return v


def _shape(shape: tuple[int | None, ...]) -> str:
    """(M, K+1, m) as numbers, "any" where any size does."""
    sizes = ["any" if s is None else str(s) for s in shape]
    return f"({', '.join(sizes)}{',' if len(sizes) == 1 else ''})"


def check_architecture_names(architectures: Any) -> list[str] | None:
    """The `architectures` argument of `estimate` as a list of names (None: the scenario's).
    One name may be a string; an empty list is refused (it would silently mean the
    scenario's list); every entry must be a string (whether it names an architecture is
    `core.names.check_architectures`)."""
    if architectures is None:
        return None
    if isinstance(architectures, str):  # "CKF", not the letters "C", "K", "F"
        return [architectures]
    if not isinstance(architectures, Sequence | np.ndarray | set | frozenset | tuple):
        raise ValidationError(
            f"architectures: expected a list of names such as ['CKF', 'MSC'], got "
            f"{_what(architectures)}"
        )
    names = list(architectures)
    if not names:
        raise ValidationError(
            "architectures: empty; name at least one (e.g. ['CKF']), or leave it out for the "
            "scenario's [estimate] architectures"
        )
    for a in names:
        if not isinstance(a, str):
            raise ValidationError(
                f"architectures: expected names (strings such as 'CKF'), got {_what(a)}"
            )
    return names


def check_simulation(
    times: Any,
    truth: Any,
    measurements: Any,
    scheduled: Any,
    covariances: Any,
    system: System,
) -> int:
    """A Simulation's arrays agree with each other and with the simulated `system` (its
    sensors by name and size, its states); returns the number of runs M."""
    times = _array(times, "sim.times", (None,))
    K1 = len(times)
    if K1 == 0 or not np.isfinite(times).all() or (np.diff(times) <= 0).any():
        raise ValidationError("sim.times: expected finite instants in increasing order, seconds")
    if not isinstance(measurements, Mapping) or not measurements:
        raise ValidationError(
            f"sim.measurements: expected {{sensor name: array (M, K+1, m)}}, got "
            f"{_what(measurements)}"
        )
    dims = {s.name: s.dim for s in system.sensors}
    missing = [s for s in dims if s not in measurements]
    if missing:
        raise ValidationError(
            f"sim.measurements: no readings of sensor {missing[0]!r} (the scenario's sensors: "
            f"{', '.join(dims)})"
        )
    M = None
    for name, z in measurements.items():
        where = f"sim.measurements[{name!r}]"
        if name not in dims:
            raise ValidationError(
                f"{where}: no sensor of that name (the scenario's: {', '.join(dims)})"
            )
        z = _array(z, where, (M, None, dims[name]))
        if z.shape[1] != K1:
            raise ValidationError(
                f"{where}: {z.shape[1]} instants, but sim.times has {K1} (shape (M, K+1, m) = "
                f"{z.shape})"
            )
        M = z.shape[0]
    if M == 0:
        raise ValidationError("sim.measurements: no runs (M = 0)")
    if truth is not None:
        _array(truth, "sim.truth", (M, K1, system.n))
    for name, at in (scheduled or {}).items():
        _array(at, f"sim.scheduled[{name!r}]", (K1,), dtype="b")
    for name, R in (covariances or {}).items():
        m = dims.get(name)
        _array(R, f"sim.covariances[{name!r}]", (K1, m, m))
    return M


def check_estimate_shapes(arch: str, e: Any, runs: int, instants: int, n: int) -> None:
    """One architecture's estimate is of this simulation's runs and instants and of the
    filter's states: `mean` (M, K+1, n), `cov` (M, K+1, n, n)."""
    where = f"estimates[{arch!r}]"
    for part, shape in (("mean", (runs, instants, n)), ("cov", (runs, instants, n, n))):
        v = getattr(e, part)
        if isinstance(v, np.ndarray) and v.dtype.kind == "f" and v.shape[:2] != shape[:2]:
            raise ValidationError(
                f"{where}.{part}: shape {v.shape} is not of this simulation's {runs} runs and "
                f"{instants} instants"
            )
        _array(v, f"{where}.{part}", shape)


def check_estimate_values(arch: str, mean: np.ndarray, cov: np.ndarray, off: int) -> None:
    """A block of runs from run `off` of an estimate: each (run, instant) is an estimate
    (finite mean and covariance, the covariance positive semidefinite) or none (NaN in both);
    an infinity is neither. `cov` is (K+1, n, n) when every run shares it."""
    where = f"estimates[{arch!r}]"
    inf_mean, inf_cov = np.isinf(mean).any(axis=-1), np.isinf(cov).any(axis=(-2, -1))
    for part, inf in (("mean", inf_mean), ("cov", inf_cov)):
        if inf.any():
            raise ValidationError(
                f"{where}.{part}: infinite at {_at(inf, off)} (an estimate is finite, or NaN "
                "in both mean and cov where there is none)"
            )
    has_mean = np.isfinite(mean).all(axis=-1)  # (runs, K+1)
    has_cov = np.isfinite(cov).all(axis=(-2, -1))  # (K+1,) shared, or (runs, K+1)
    half = has_mean != has_cov
    if half.any():
        nan_in = "cov" if (half & has_mean).any() else "mean"
        raise ValidationError(
            f"{where}: NaN in the {nan_in} but not in the other at {_at(half, off)} (NaN marks "
            "no estimate: in both mean and cov, or in neither)"
        )
    bad = not_a_covariance(cov)
    if bad.any():
        raise ValidationError(
            f"{where}.cov: not positive semidefinite at {_at(bad, off)} (a negative variance, "
            "or a negative eigenvalue of its correlation matrix)"
        )


def _at(mask: np.ndarray, off: int) -> str:
    """Where the first True of a (runs, K+1) mask (or a shared (K+1,) one) is, for a message."""
    if mask.ndim == 1:
        return f"instant {int(np.flatnonzero(mask)[0])}"
    run, k = (int(i[0]) for i in np.nonzero(mask))
    return f"run {off + run}, instant {k}"
