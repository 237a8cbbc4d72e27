"""Monte Carlo simulation of eqs. (12)-(13): truth trajectories and stacked sensor measurements.

Random numbers come from one independent stream per chunk of runs (child c of the scenario seed's
SeedSequence), so the runs a seed produces do not depend on how a caller splits them into blocks:
runs [a, b) are the same whether drawn alone or as part of a larger block. A chunk holds at most
SEED_CHUNK runs and about CHUNK_RUN_STEPS run-steps, so that long horizons stay small in memory.
:func:`chunked` is that loop, shared with the identity kind (:mod:`fusionlog.core.identity`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

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


def _draw(
    system: System, steps: int, rng: np.random.Generator, R: int, measures: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Truth (R, K+1, n) and measurements (R, K+1, m) of one chunk of R runs; NaN where a
    sensor does not measure (`measures`, (K+1, S)) or its measurement was lost."""
    n, m = system.n, system.m
    init = system.truth_initial
    Q = system.Q
    G = system.G if system.G is not None else np.eye(n)
    # An overflow is reported below, as one error rather than numpy's warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        # Draw order is part of the reproducibility contract: x0, then w, then v.
        e0 = rng.standard_normal((R, n))
        if system.time_invariant:
            w = rng.standard_normal((R, steps, Q.shape[0])) @ psd_sqrt(Q).T @ G.T
        else:  # irregular instants: the noise of each interval (in state space, Qs)
            w = rng.standard_normal((R, steps, n))
            for k in range(steps):
                w[:, k] = w[:, k] @ psd_sqrt(system.GQG_at(k + 1)).T
        v = rng.standard_normal((R, steps + 1, m)) @ psd_sqrt(system.R).T
        x = np.empty((R, steps + 1, n))
        x[:, 0] = init.mean + e0 @ psd_sqrt(init.cov).T
        for k in range(steps):
            try:
                x[:, k + 1] = system.propagate(x[:, k], k + 1) + w[:, k]
            except NumericalError as e:  # a motion model's own refusal (the turn's angle)
                raise NumericalError(f"simulation: the true state at step {k + 1}: {e}") from None
        z = system.h(x) + v
        if not system.linear:  # a bearing read with its noise is still in (-pi, pi]
            z = system.residual(z, np.zeros(z.shape[-1]))
    _require_finite(x, z)
    dropout = np.array([s.timing.dropout for s in system.sensors])
    if measures is not None or dropout.any():
        present = np.ones((R, steps + 1, len(system.sensors)), dtype=bool)
        if measures is not None:
            present &= measures
        if dropout.any():
            # Drawn last, and only when some sensor drops: scenarios without dropouts keep
            # the numbers they always had.
            present &= rng.random((R, steps + 1, len(dropout))) >= dropout
        for j, sl in enumerate(system.sensor_slices):
            z[:, :, sl][~present[:, :, j]] = np.nan
    return x, z


def _require_finite(x: np.ndarray, z: np.ndarray, k0: int = 0) -> None:
    """Non-finite values would be read as missing measurements downstream: refuse them, naming
    the first step (x, z: (runs, w, .) of the instants from k0)."""
    for what, a in (("the true state", x), ("the measurement", z)):
        if not np.isfinite(a).all():
            finite = np.isfinite(a).all(axis=(0, 2))
            raise NumericalError(
                f"simulation: {what} overflows at step {k0 + int(np.argmin(finite))} "
                "(beyond the float range, about 1.8e308)"
            )


def chunked(
    draw: Callable[[np.random.Generator, int], tuple[np.ndarray, ...]],
    steps: int,
    seed: int,
    run_offset: int,
    runs: int,
    stream: tuple[int, ...] = (),
) -> tuple[np.ndarray, ...]:
    """Runs [run_offset, run_offset + runs) of a chunked Monte Carlo draw, for either kind.

    Chunk c of chunk_runs(steps) runs has its own stream, child c of the seed's SeedSequence
    (spawn key (c, *stream): another `stream` draws apart from, and without moving, the first);
    draw(rng, size) returns arrays whose first axis is the chunk's `size` runs. Each wanted
    chunk is drawn whole and sliced, so a run's numbers never depend on the caller's blocks.
    """
    if runs < 1 or run_offset < 0:
        raise ValueError(f"runs [{run_offset}, {run_offset + runs}) is not a range of runs")
    size = chunk_runs(steps)
    first, last = run_offset // size, (run_offset + runs - 1) // size
    parts = []
    for c in range(first, last + 1):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(c, *stream)))
        lo = max(run_offset - c * size, 0)
        hi = min(run_offset + runs - c * size, size)
        parts.append([a[lo:hi] for a in draw(rng, size)])
    return tuple(np.concatenate(arrays) for arrays in zip(*parts, strict=True))


def simulate(
    system: System,
    steps: int,
    seed: int,
    run_offset: int,
    runs: int,
    measures: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Truth x (runs, K+1, n) and measurements z (runs, K+1, m) for runs [run_offset, +runs).

    `system` is on its instants (`System.on_times`); `measures` (K+1, S) says which sensor
    measures at which instant (None: all, always). A measurement that is not made, or lost
    (each independently with its sensor's `timing.dropout`, drawn from the same stream), is
    NaN."""

    def draw(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
        return _draw(system, steps, rng, size, measures)

    return chunked(draw, steps, seed, run_offset, runs)


def _advanced(seed: int, normals: int) -> np.random.Generator:
    """Run 0's stream (child 0 of the seed's SeedSequence) after `normals` standard normals,
    drawn in pieces (the ziggurat may take more than one word for a normal: no jump)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,)))
    for a in range(0, normals, 1 << 16):  # 0.5 MB at a time
        rng.standard_normal(min(1 << 16, normals - a))
    return rng


def one_run_blocks(
    system: System, steps: int, seed: int, block: int, measures: np.ndarray | None = None
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """The truth and measurements of run 0 (`simulate(system, steps, seed, 0, 1, measures)`:
    the same numbers) in blocks of `block` instants, (k0, k1, x (1, w, n), z (1, w, m)): f and
    h as `_draw` applies them (a bearing wrapped), the noise of each interval where the
    instants are irregular (`System.GQG_at`), NaN where `measures` (K+1, S) says a sensor does
    not measure or its reading is lost (`timing.dropout`) (issue 34: a 10^6-instant log in
    bounded memory). The stream's draw order is x0, every w, every v, then the dropouts'
    uniforms (`_draw`, each of the chunk's runs with run 0's values first), so w is drawn block
    by block from one generator while a second one, advanced past x0 and every w, draws v, and
    a third, advanced past v too, the dropouts: nothing of the length of the log is kept."""
    n, m = system.n, system.m
    invariant = system.time_invariant
    q = system.Q.shape[0] if invariant else n
    size = chunk_runs(steps)  # the runs drawn together from the stream: run 0's values first
    skip_w = size * n  # x0 of every run of the chunk
    skip_v = skip_w + size * steps * q  # then w
    rng, rng_v = _advanced(seed, 0), _advanced(seed, skip_v)
    dropout = np.array([s.timing.dropout for s in system.sensors])
    rng_d = _advanced(seed, skip_v + size * (steps + 1) * m) if dropout.any() else None
    init = system.truth_initial
    G = system.G if system.G is not None else np.eye(n)
    LQ, LR = psd_sqrt(system.Q).T, psd_sqrt(system.R).T

    def chunk(row: np.ndarray) -> np.ndarray:
        """Run 0's row (1, .) as the chunk's `size` rows: `_draw`'s products are of the
        chunk's runs, and BLAS may round one row of a matrix product otherwise (gemv)."""
        return np.repeat(row, size, axis=0) if size > 1 else row

    with np.errstate(over="ignore", invalid="ignore"):
        x_prev = (init.mean + rng.standard_normal((size, n)) @ psd_sqrt(init.cov).T)[:1]
    for k0 in range(0, steps + 1, block):
        k1 = min(k0 + block, steps + 1)
        first = max(k0, 1)  # the first instant of the block reached by a transition
        with np.errstate(over="ignore", invalid="ignore"):
            if invariant:
                w = rng.standard_normal((1, k1 - first, q)) @ LQ @ G.T
            else:  # as `_draw`: each interval's noise in state space
                w = rng.standard_normal((1, k1 - first, n))
                for k in range(first, k1):
                    w[:, k - first] = (chunk(w[:, k - first]) @ psd_sqrt(system.GQG_at(k)).T)[:1]
            x = np.empty((1, k1 - k0, n))
            if k0 == 0:
                x[:, 0] = x_prev
            for k in range(first, k1):
                x_prev = x[:, k - k0] = system.propagate(chunk(x_prev), k)[:1] + w[:, k - first]
            z = system.h(x) + rng_v.standard_normal((1, k1 - k0, m)) @ LR
            if not system.linear:  # as `_draw`: a bearing read with its noise in (-pi, pi]
                z = system.residual(z, np.zeros(m))
        _require_finite(x, z, k0)
        present = np.ones((k1 - k0, len(system.sensors)), dtype=bool)
        if measures is not None:
            present &= measures[k0:k1]
        if rng_d is not None:  # drawn as `_draw` draws them, after every v
            present &= rng_d.random((1, k1 - k0, len(dropout)))[0] >= dropout
        for j, sl in enumerate(system.sensor_slices):
            z[:, ~present[:, j], sl] = np.nan
        yield k0, k1, x, z
