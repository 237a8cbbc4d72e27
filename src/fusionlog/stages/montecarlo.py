"""The Monte Carlo of a state scenario in blocks of runs, without files: what a Dask worker (or
this process) computes for ``fusionlog sweep`` and ``fusionlog run --workers``.

A block is simulated with the kind's own hook (so its runs are exactly those ``fusionlog run``
writes for the same seed: the random streams belong to chunks of runs, not to blocks, see
:mod:`fusionlog.core.simulate`), estimated with each architecture's plan, and reduced at once
to the metric sums of :class:`fusionlog.core.metrics.MetricsAccumulator`. Only those sums leave
the worker (a few kilobytes per architecture for the paper's example), never the estimates;
the client merges them in block order, so the merged sums, and every number made from them, do
not depend on how many workers there were or which finished first.

Nothing here imports Dask: the functions are plain, picklable by reference, and run the same
in a worker process, a worker thread or this process. Whoever runs them passes the plan caches
of the jobs it has seen (`plans`, a `driver.JobPlans`: the executors of `.distributed` keep
one in this process and one on each Dask worker), so the blocks after the first of a job do not
recompile; a call without one compiles afresh.
"""

from __future__ import annotations

import functools
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from fusionlog.core.architectures import Estimate
from fusionlog.core.late_policy import random_delays
from fusionlog.driver import JobPlans, PlanCache, estimate_block
from fusionlog.errors import NumericalError
from fusionlog.memory import keep_freed_memory
from fusionlog.scenario import NonlinearScenario, Scenario

from .common import block_runs
from .kinds import kind_of
from .trajectory_eval import trajectory_block

__all__ = [
    "BlockSums",
    "Job",
    "block_estimates",
    "block_sums",
    "blocks",
    "exact_mask",
    "expected_overall",
    "fold",
    "point_expected",
]

T = TypeVar("T")


@dataclass(frozen=True)
class Job:
    """What a worker needs for the blocks of one scenario: the scenario (with its seed and
    runs), the architectures, and a token naming the job in the worker's plan cache (unique
    per sweep point or run: workers of a long-lived cluster serve many)."""

    scenario: Scenario
    archs: tuple[str, ...]
    token: str
    #: also sum each run's exact statistics given its measurement pattern (runs whose patterns
    #: differ: dropouts), the expected values conditional on the drawn patterns
    conditional: bool = False
    #: how an error names the job: a sweep's grid point (`GridPoint.where`), else the file
    where: str | None = None


@dataclass
class BlockSums:
    """A block's contribution: the metric sums of each architecture (workspaces dropped), the
    measurement pattern its runs shared (``np.packbits`` of the (K+1, m) mask, None when runs
    differ) and the seconds the worker spent on it."""

    run_offset: int
    runs: int
    sums: dict[str, Any]  # arch -> MetricsAccumulator
    pattern: bytes | None
    seconds: float = 0.0
    #: arch -> core.exact.ConditionalExpected of the block's runs (conditional jobs only)
    expected: dict[str, Any] | None = None
    #: arch -> core.trajectory.TrajectorySums (scenarios with position states)
    trajectory: dict[str, Any] | None = None


_LOCK = threading.Lock()
#: Scratch arrays of the metric sums, one set per thread (a `dask worker` may run several
#: tasks at once in threads; a workspace must not be shared between them).
_LOCAL = threading.local()


def _one_blas_thread(fn: Callable[..., T]) -> Callable[..., T]:
    """Run `fn` with BLAS on one thread. A multithreaded BLAS splits the reductions of the
    metric sums (matrix-vector products over runs) by its thread count, which changes their
    last bits: with one thread a block's sums are the same in this process (--workers 0), in
    a Dask worker (whose nanny sets one thread) and in a `dask worker` started by hand. The
    parallelism is across the workers instead. A task also sets its process's allocator to
    keep freed memory (`fusionlog.memory`: a worker process is fusionlog's own)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> T:
        keep_freed_memory()
        try:
            with _blas_controller().limit(limits=1, user_api="blas"):
                return fn(*args, **kwargs)
        except NumericalError as e:  # the core names the architecture and step; the file here
            job = args[0] if args and isinstance(args[0], Job) else None
            if job is None:
                raise
            where = job.where or job.scenario.path or job.scenario.name
            msg, file = str(e), f"{job.scenario.path}: "
            if msg.startswith(f"{where}: "):
                raise
            if msg.startswith(file):  # named the file already (a simulation): name the point
                msg = msg[len(file) :]
            raise NumericalError(f"{where}: {msg}") from None

    return wrapper


_CONTROLLER: tuple[int, Any] | None = None


def _blas_controller() -> Any:
    """threadpoolctl's view of the loaded BLAS libraries, refreshed when modules were
    imported since (scipy brings a BLAS of its own)."""
    global _CONTROLLER
    from threadpoolctl import ThreadpoolController

    with _LOCK:
        if _CONTROLLER is None or _CONTROLLER[0] != len(sys.modules):
            _CONTROLLER = (len(sys.modules), ThreadpoolController())
        return _CONTROLLER[1]


def blocks(scenario: Scenario, requested: int | None = None) -> list[tuple[int, int]]:
    """(run_offset, runs) of the scenario's blocks: as many as the stages' block size
    (:func:`.common.block_runs`, about a million run-steps) needs, of equal size rounded up to
    whole random-number chunks. A function of the scenario alone, never of the cluster."""
    from fusionlog.core.simulate import chunk_runs

    K, M = scenario.instants - 1, scenario.runs
    most = block_runs(K, M, requested)
    n = -(-M // most)
    size = -(-M // n)
    if requested is None:  # whole chunks: no chunk drawn twice by two blocks
        chunk = chunk_runs(K)
        size = min(M, -(-size // chunk) * chunk)
    return [(off, min(size, M - off)) for off in range(0, M, size)]


def _plans(job: Job, plans: JobPlans | None) -> PlanCache:
    """The job's plan cache among `plans` (its system on the scenario's instants)."""
    sc = job.scenario
    return (JobPlans() if plans is None else plans).of(job.token, sc.system, sc.times)


def _simulated(job: Job, run_offset: int, runs: int) -> tuple[np.ndarray, np.ndarray, Any]:
    """Truth (runs, K+1, n), stacked readings (runs, K+1, m; NaN where absent) and when they
    arrived (None: on time) of runs [run_offset, run_offset + runs), simulated with the
    kind's hooks (those `run` writes)."""
    sc = job.scenario
    kind = kind_of(sc.kind)
    x, zs = kind.simulate(sc, run_offset, runs)
    return x, np.concatenate(zs, axis=-1), kind.arrivals(sc, run_offset, runs)


@_one_blas_thread
def block_estimates(
    job: Job, run_offset: int, runs: int, plans: JobPlans | None = None
) -> tuple[np.ndarray, np.ndarray, dict[str, Estimate], np.ndarray | None]:
    """Truth, the stacked readings, each architecture's estimates and the shared measurement
    pattern (None when runs differ) of a block: `estimate_block`, as the estimate stage."""
    x, z, arrivals = _simulated(job, run_offset, runs)
    c = _plans(job, plans)
    block = estimate_block(c.system, job.archs, z, cache=c, arrivals=arrivals)
    return x, z, block.estimates, block.pattern


@_one_blas_thread
def block_sums(job: Job, run_offset: int, runs: int, plans: JobPlans | None = None) -> BlockSums:
    """The metric sums of one block of runs (the task a worker runs): `estimate_block` with
    the truth, the estimates dropped once reduced (and, for a conditional job, its runs'
    exact sums given their patterns)."""
    t0 = time.perf_counter()
    x, z, arrivals = _simulated(job, run_offset, runs)
    c = _plans(job, plans)
    ws = getattr(_LOCAL, "workspace", None)
    if ws is None:
        from fusionlog.core.metrics import MetricsWorkspace

        ws = _LOCAL.workspace = MetricsWorkspace()
    expected_of = c.system if job.conditional else None
    sc = job.scenario
    keep = sc.trajectory is not None  # the APE/RPE need the means, reduced here
    block = estimate_block(
        c.system, job.archs, z, truth=x, expected_of=expected_of, cache=c, workspace=ws,
        keep=keep, arrivals=arrivals,
    )  # fmt: skip
    key = None if block.pattern is None else np.packbits(block.pattern).tobytes()
    assert block.sums is not None
    traj = None
    if keep:
        means = {a: e.mean for a, e in block.estimates.items()}
        traj = trajectory_block(sc, sc.times, x, means, run_offset, sc.path or sc.name)
    seconds = time.perf_counter() - t0
    return BlockSums(run_offset, runs, block.sums, key, seconds, block.expected, traj)


def fold(
    totals: dict[str, Any],
    block: BlockSums,
    expected: dict[str, Any] | None = None,
    trajectory: dict[str, Any] | None = None,
) -> None:
    """Add a block's sums to running totals by architecture (the first block's become the
    totals), and its conditional expected sums to `expected` and trajectory sums to
    `trajectory` when given. Callers fold blocks in block order: the same additions for any
    cluster."""
    parts_of = ((totals, block.sums), (expected, block.expected), (trajectory, block.trajectory))
    for into, parts in parts_of:
        if into is None or parts is None:
            continue
        for a, acc in parts.items():
            if a in into:
                into[a].merge(acc)
            else:
                into[a] = acc


def exact_mask(scenario: Scenario) -> tuple[bool, np.ndarray | None]:
    """(whether an exact analysis exists, the measurement mask it needs) from the scenario
    alone: the sensors' schedule gives a pattern shared by every run (None: complete); a
    sensor with dropouts makes the runs differ, and then there is none (yet: a per-run exact
    analysis would average each run's)."""
    system = scenario.system
    if not system.linear or any(s.timing.dropout > 0 for s in system.sensors):
        return False, None
    if random_delays(system):  # what arrives when differs per run, as with dropouts
        return False, None
    measures = scenario.schedule.measures
    if measures.all():
        return True, None
    return True, np.repeat(measures, [s.dim for s in system.sensors], axis=1)


def expected_overall(ex: Any) -> dict[str, float | None]:
    """Overall expected MSE (eq. 45 on the exact per-step values), ANEES and DM of an exact
    analysis (`core.exact.Expected`, or a run average `ConditionalExpected`): means over the
    steps where the architecture reports a covariance (some run does), which are the steps
    where its Monte Carlo estimates are defined, the steps `MetricsResult.expected_overall`
    averages over (non-finite entries skipped likewise)."""
    from fusionlog.core.exact import ConditionalExpected
    from fusionlog.core.linalg import finite_mean
    from fusionlog.core.metrics import expected_means

    # a run average counts the runs defined at each step
    valid = ex.count > 0 if isinstance(ex, ConditionalExpected) else ex.defined
    mse = expected_means(ex.mse_per_state, valid)
    return {"mse": mse, "anees": finite_mean(ex.nees[valid]), "dm": finite_mean(ex.dm[valid])}


@_one_blas_thread
def point_expected(job: Job, plans: JobPlans | None = None) -> dict[str, dict[str, Any] | None]:
    """The exact expected MSE, ANEES and DM of every architecture of a scenario, and its
    bound check under "bound" (`core.bound.bound_summary`); None where there is no exact
    analysis: runs with different measurement patterns."""
    from fusionlog.core.exact import analyse

    ok, mask = exact_mask(job.scenario)
    if not ok:
        return dict.fromkeys(job.archs)
    from fusionlog.core.bound import bound_summary

    c = _plans(job, plans)
    out: dict[str, dict[str, Any] | None] = {}
    for a in job.archs:
        ex = analyse(c.plan(a, mask), c.system)
        # the bound check rides beside the expected values (`sweep_outputs` moves it out)
        out[a] = expected_overall(ex) | {"bound": bound_summary(ex.bound)}
    return out


def simulated_readings(
    scenario: Any, run_offset: int, runs: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Truth and each sensor's readings {topic: (runs, K+1, dim)} of runs [run_offset, +runs),
    simulated: what the PCRB needs of runs whose estimates live elsewhere (Dask workers)."""
    from fusionlog.io.mcap import sensor_topic

    x, zs = kind_of(scenario.kind).simulate(scenario, run_offset, runs)
    names = [s.name for s in scenario.system.sensors]
    return x, {sensor_topic(n): z for n, z in zip(names, zs, strict=True)}


def scenario_bound(scenario: Any) -> dict[str, Any] | None:
    """summary.json's "pcrb" of a scenario with a nonlinear model, from all its runs simulated
    block by block (the bound needs their truth and which measurements they made, no
    estimate: a sweep's point, computed where the points are summarised); None when the
    model is linear (its exact analysis stands instead)."""
    if not isinstance(scenario, NonlinearScenario):
        return None
    from .evaluator.pcrb_part import PcrbPart

    part = PcrbPart(scenario.system, scenario.times)
    for off, n in blocks(scenario):
        part.add_readings(*simulated_readings(scenario, off, n))
    return part.summary()
