"""Monte Carlo simulation of eqs. (12)-(13): truth trajectories and stacked sensor measurements.

Random numbers come from one independent stream per chunk of runs (child c of the scenario seed's
SeedSequence), so the runs a seed produces do not depend on how a caller splits them into blocks:
runs [a, b) are the same whether drawn alone or as part of a larger block. A chunk holds at most
SEED_CHUNK runs and about CHUNK_RUN_STEPS run-steps, so that long horizons stay small in memory.
"""

from __future__ import annotations

import numpy as np

from ..errors import NumericalError
from .model import System

SEED_CHUNK = 1024
CHUNK_RUN_STEPS = 1 << 18


def chunk_runs(steps: int) -> int:
    """Runs per random stream for a horizon of `steps` (a function of the scenario only)."""
    return int(np.clip(CHUNK_RUN_STEPS // (steps + 1), 1, SEED_CHUNK))


def psd_sqrt(C: np.ndarray) -> np.ndarray:
    """A factor L with L L^T = C for a PSD C (Cholesky, or eigen-decomposition when singular)."""
    try:
        return np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(C)
        return V * np.sqrt(np.clip(w, 0.0, None))


def _chunk(system: System, steps: int, seed: int, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(chunk,)))
    R, n, m = chunk_runs(steps), system.n, system.m
    init = system.truth_initial
    Q = system.Q
    G = system.G if system.G is not None else np.eye(n)
    # An overflow is reported below, as one error rather than numpy's warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        # Draw order is part of the reproducibility contract: x0, then w, then v.
        e0 = rng.standard_normal((R, n))
        w = rng.standard_normal((R, steps, Q.shape[0])) @ psd_sqrt(Q).T @ G.T
        v = rng.standard_normal((R, steps + 1, m)) @ psd_sqrt(system.R).T
        x = np.empty((R, steps + 1, n))
        x[:, 0] = init.mean + e0 @ psd_sqrt(init.cov).T
        for k in range(steps):
            x[:, k + 1] = x[:, k] @ system.F.T + w[:, k]
        z = x @ system.H.T + v
    for what, a in (("the true state", x), ("the measurement", z)):
        if not np.isfinite(a).all():
            # Non-finite values would be read as missing measurements downstream: refuse them.
            finite = np.isfinite(a).all(axis=(0, 2))
            raise NumericalError(
                f"simulation: {what} overflows at step {int(np.argmin(finite))} "
                "(beyond the float range, about 1.8e308)"
            )
    return x, z


def simulate(
    system: System, steps: int, seed: int, run_offset: int, runs: int
) -> tuple[np.ndarray, np.ndarray]:
    """Truth x (runs, K+1, n) and measurements z (runs, K+1, m) for runs [run_offset, +runs)."""
    size = chunk_runs(steps)
    first, last = run_offset // size, (run_offset + runs - 1) // size
    xs, zs = [], []
    for c in range(first, last + 1):
        x, z = _chunk(system, steps, seed, c)
        lo = max(run_offset - c * size, 0)
        hi = min(run_offset + runs - c * size, size)
        xs.append(x[lo:hi])
        zs.append(z[lo:hi])
    return np.concatenate(xs), np.concatenate(zs)
