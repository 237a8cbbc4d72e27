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
in a worker process, a worker thread or this process. A worker keeps the systems and plans of
the jobs it has seen (``_CACHE``), so the blocks after the first of a job do not recompile.
"""

from __future__ import annotations

import functools
import json
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from fusionlog.core.architectures import Estimate, Plan, build_plan, run_plan, shared_pattern
from fusionlog.core.model import System
from fusionlog.memory import keep_freed_memory
from fusionlog.scenario import Scenario

from .common import block_runs
from .kinds import kind_of

__all__ = [
    "BlockSums",
    "Job",
    "block_estimates",
    "block_sums",
    "blocks",
    "exact_mask",
    "expected_overall",
    "fold",
    "pattern_provenance",
    "point_expected",
]

T = TypeVar("T")

#: Jobs whose compiled systems and plans a worker keeps (least recently used dropped first).
CACHED_JOBS = 8


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


@dataclass
class _Compiled:
    system: System  # on the scenario's instants
    plans: dict[tuple[str, bytes], Plan] = field(default_factory=dict)


_CACHE: OrderedDict[str, _Compiled] = OrderedDict()
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
        with _blas_controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

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


def _compiled(job: Job) -> _Compiled:
    with _LOCK:
        c = _CACHE.get(job.token)
        if c is not None:
            _CACHE.move_to_end(job.token)
            return c
    sc = job.scenario
    c = _Compiled(sc.system.on_times(sc.times))
    with _LOCK:
        c = _CACHE.setdefault(job.token, c)
        while len(_CACHE) > CACHED_JOBS:
            _CACHE.popitem(last=False)
    return c


@_one_blas_thread
def block_estimates(
    job: Job, run_offset: int, runs: int
) -> tuple[np.ndarray, np.ndarray, dict[str, Estimate], np.ndarray | None]:
    """Truth (runs, K+1, n), the stacked readings (runs, K+1, m; NaN where absent), each
    architecture's estimates and the shared measurement pattern (None when runs differ) of runs
    [run_offset, run_offset + runs): as the estimate stage computes them."""
    x, z, plans, pattern = _block(job, run_offset, runs)
    return x, z, {a: run_plan(plan, z) for a, plan in plans.items()}, pattern


def _block(
    job: Job, run_offset: int, runs: int
) -> tuple[np.ndarray, np.ndarray, dict[str, Plan], np.ndarray | None]:
    """Truth, readings, each architecture's plan and the shared pattern of a block: one plan
    per architecture and shared pattern (compiled once per job), or one built for the block's
    runs when their patterns differ (what `core.architectures.estimate` does)."""
    sc = job.scenario
    c = _compiled(job)
    x, zs = kind_of(sc.kind).simulate(sc, run_offset, runs)
    z = np.concatenate(zs, axis=-1)
    pattern = shared_pattern(z)
    K = sc.instants - 1
    plans = {
        a: _plan(job, c, a, pattern)
        if pattern is not None
        else build_plan(c.system, a, K, ~np.isnan(z))
        for a in job.archs
    }
    return x, z, plans, pattern


def _plan(job: Job, c: _Compiled, arch: str, pattern: np.ndarray) -> Plan:
    """The architecture's plan for a measurement pattern shared by all runs (compiled once per
    job and pattern in this process; the exact analysis and the blocks share it)."""
    key = (arch, np.packbits(pattern).tobytes())
    plan = c.plans.get(key)
    if plan is None:
        K = job.scenario.instants - 1
        plan = build_plan(c.system, arch, K, None if pattern.all() else pattern)
        c.plans[key] = plan
    return plan


@_one_blas_thread
def block_sums(job: Job, run_offset: int, runs: int) -> BlockSums:
    """The metric sums of one block of runs (the task a worker runs)."""
    from fusionlog.core.metrics import MetricsAccumulator, MetricsWorkspace

    t0 = time.perf_counter()
    x, z, plans, pattern = _block(job, run_offset, runs)
    ws = getattr(_LOCAL, "workspace", None)
    if ws is None:
        ws = _LOCAL.workspace = MetricsWorkspace()
    sums = {}
    empty = MetricsWorkspace()
    for a, plan in plans.items():
        e = run_plan(plan, z)
        acc = MetricsAccumulator(x.shape[1], x.shape[2], workspace=ws)
        acc.add(x, e.mean, e.cov)
        acc.workspace = empty  # the scratch arrays stay here: only the sums travel
        sums[a] = acc
    expected = _conditional(job, plans, runs) if job.conditional else None
    key = None if pattern is None else np.packbits(pattern).tobytes()
    return BlockSums(run_offset, runs, sums, key, time.perf_counter() - t0, expected)


def _conditional(job: Job, plans: dict[str, Plan], runs: int) -> dict[str, Any]:
    """Each run's exact statistics given its pattern, summed (`core.exact.ConditionalExpected`,
    as the state evaluator sums them): a plan shared by the block's runs is analysed once."""
    from fusionlog.core.exact import ConditionalExpected, analyse

    c = _compiled(job)
    out = {}
    for a, plan in plans.items():
        ce = ConditionalExpected(job.scenario.instants, c.system.n)
        ce.add(analyse(plan, c.system), 1 if plan.per_run else runs)
        out[a] = ce
    return out


def fold(totals: dict[str, Any], block: BlockSums, expected: dict[str, Any] | None = None) -> None:
    """Add a block's sums to running totals by architecture (the first block's become the
    totals), and its conditional expected sums to `expected` when given. Callers fold blocks
    in block order: the same additions for any cluster."""
    for into, parts in ((totals, block.sums), (expected, block.expected)):
        if into is None or parts is None:
            continue
        for a, acc in parts.items():
            if a in into:
                into[a].merge(acc)
            else:
                into[a] = acc


def pattern_provenance(patterns: Sequence[bytes | None], shape: tuple[int, int]) -> dict[str, str]:
    """The ``measurement_pattern`` the estimate stage records (its Estimator.provenance), from
    the blocks' shared patterns: "complete", the mask as JSON, or "per-run" when any block's
    runs differed or two blocks had different patterns."""
    if not patterns or any(p is None for p in patterns) or len(set(patterns)) > 1:
        return {"measurement_pattern": "per-run"}
    mask = np.unpackbits(np.frombuffer(patterns[0], dtype=np.uint8))[: shape[0] * shape[1]]
    mask = mask.reshape(shape).astype(bool)
    if mask.all():
        return {"measurement_pattern": "complete"}
    return {"measurement_pattern": json.dumps(mask.astype(int).tolist())}


def exact_mask(scenario: Scenario) -> tuple[bool, np.ndarray | None]:
    """(whether an exact analysis exists, the measurement mask it needs) from the scenario
    alone: the sensors' schedule gives a pattern shared by every run (None: complete); a
    sensor with dropouts makes the runs differ, and then there is none (yet: a per-run exact
    analysis would average each run's)."""
    system = scenario.system
    if any(s.timing.dropout > 0 for s in system.sensors):
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
    # a run average (ConditionalExpected) counts the runs defined at each step
    valid = ex.count > 0 if hasattr(ex, "count") else ex.defined

    def mean(a: np.ndarray) -> float | None:
        a = a[np.isfinite(a)]
        return float(a.mean()) if a.size else None

    per_state = [mean(ex.mse_per_state[valid, i]) for i in range(ex.mse_per_state.shape[1])]
    mse = None if any(v is None for v in per_state) else float(np.mean(per_state))
    return {"mse": mse, "anees": mean(ex.nees[valid]), "dm": mean(ex.dm[valid])}


@_one_blas_thread
def point_expected(job: Job) -> dict[str, dict[str, float | None] | None]:
    """The exact expected MSE, ANEES and DM of every architecture of a scenario (None where
    there is no exact analysis: runs with different measurement patterns)."""
    from fusionlog.core.exact import analyse

    ok, mask = exact_mask(job.scenario)
    if not ok:
        return dict.fromkeys(job.archs)
    c = _compiled(job)
    if mask is None:
        mask = np.ones((job.scenario.instants, c.system.m), dtype=bool)
    return {a: expected_overall(analyse(_plan(job, c, a, mask), c.system)) for a in job.archs}
