"""Shared fixtures: random linear Gaussian systems for property tests."""

from __future__ import annotations

import numpy as np

from fusionlog.core.model import Prior, Sensor, System


def random_spd(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T / n + 0.5 * np.eye(n))


def random_system(
    rng: np.random.Generator,
    n: int,
    sensor_dims: list[int],
    *,
    prior: bool = True,
    correlated: bool = False,
) -> System:
    """A random stable model with sensors of the given output sizes."""
    F = np.eye(n) + 0.3 * rng.standard_normal((n, n)) / np.sqrt(n)
    F /= max(1.0, np.max(np.abs(np.linalg.eigvals(F))) / 1.02)
    Q = random_spd(rng, n, 0.1)
    sensors = tuple(
        Sensor(f"s{j + 1}", rng.standard_normal((m, n)), random_spd(rng, m, 0.5))
        for j, m in enumerate(sensor_dims)
    )
    cross = {}
    if correlated and len(sensors) >= 2:
        R0, R1 = sensors[0].R, sensors[1].R
        # A cross-covariance small enough that the block R stays positive definite.
        L0, L1 = np.linalg.cholesky(R0), np.linalg.cholesky(R1)
        C = rng.uniform(-0.5, 0.5, (R0.shape[0], R1.shape[0]))
        C *= 0.6 / max(1.0, np.linalg.norm(C, 2))
        cross[(0, 1)] = L0 @ C @ L1.T
    pr = Prior(rng.standard_normal(n), random_spd(rng, n)) if prior else None
    init = pr if prior else Prior(rng.standard_normal(n), random_spd(rng, n))
    return System(F=F, Q=Q, sensors=sensors, prior=pr, cross_R=cross, initial=init)
