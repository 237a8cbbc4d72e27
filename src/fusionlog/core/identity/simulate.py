"""Monte Carlo simulation of an identity scenario: true classes and sensor reports (seed 004).

The true class of a run is drawn from the prior; at every step each sensor draws a report from
the row of its confusion matrix for that class, independently of the other sensors and steps
(the conditional independence of Challa & Koks's eq. 36).

Random numbers come from one stream per chunk of runs, through the same
:func:`fusionlog.core.simulate.chunked` as the state kind, so the runs a seed produces do not
depend on the block size. Draw order per chunk (part of the reproducibility contract): one
uniform per run (the class), then one per (run, step, sensor) (the reports), both turned into
indices by the inverse CDF.
"""

from __future__ import annotations

import numpy as np

from fusionlog.core.simulate import chunked

from .model import IdentitySystem

__all__ = ["simulate"]


def _inverse_cdf(probs: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Index j with cdf_{j-1} <= u < cdf_j, for rows probs (..., J) and uniforms u (...)."""
    cdf = np.cumsum(probs, axis=-1)[..., :-1]
    return (u[..., None] >= cdf).sum(axis=-1)


def _draw(
    system: IdentitySystem, steps: int, rng: np.random.Generator, R: int
) -> tuple[np.ndarray, np.ndarray]:
    """True classes (R,) and report indices (R, K+1, S) of one chunk of R runs."""
    S = len(system.sensors)
    u0 = rng.random(R)
    u = rng.random((R, steps + 1, S))
    truth = _inverse_cdf(np.asarray(system.prior), u0)
    reports = np.empty((R, steps + 1, S), dtype=np.int64)
    for s, sensor in enumerate(system.sensors):
        rows = sensor.confusion[truth][:, None, :]  # (R, 1, reports)
        reports[:, :, s] = _inverse_cdf(rows, u[:, :, s])
    return truth, reports


def simulate(
    system: IdentitySystem, steps: int, seed: int, run_offset: int, runs: int
) -> tuple[np.ndarray, np.ndarray]:
    """True class indices (runs,) and report indices (runs, K+1, S) for runs [run_offset, +runs).

    A report index is a position in that sensor's ``reports`` (never "no report": the
    simulation has no gaps).
    """
    truth, reports = chunked(
        lambda rng, size: _draw(system, steps, rng, size), steps, seed, run_offset, runs
    )
    return truth, reports
