"""The file-free estimation driver: one block of runs through the architectures.

`estimate_block` is the one function that estimates a block: every caller (the estimate and
run stages, the sweep's and `run --workers`' Dask tasks, the Python API) hands it arrays --
the stacked measurements z (runs, K+1, m) of eq. (30) with NaN where a component is missing
-- and gets back each architecture's estimates and, given the truth, the block's mergeable
metric sums (`core.metrics.MetricsAccumulator`, eqs. 44-47) and, given a truth model, the
exact statistics of each run conditional on its measurement pattern
(`core.exact.ConditionalExpected`). It sits above the math of `core` (the plans, their
executor and exact analysis, the replay path, the EKF/UKF lanes), which never calls back up;
the plans it keeps across blocks are in a `PlanCache` the caller passes (`cache`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusionlog.core.architectures import Estimate, Plan, run_plan, shared_pattern
from fusionlog.core.exact import ConditionalExpected, analyse
from fusionlog.core.model import System
from fusionlog.core.nonlinear import estimate as nonlinear_estimate
from fusionlog.core.reference import reference_paths

from .plans import PlanCache

__all__ = ["Block", "conditional_sums", "estimate_block"]


@dataclass
class Block:
    """What `estimate_block` returns for a block of runs.

    `estimates[arch]`: mean (runs, K+1, n), cov (K+1, n, n) shared or (runs, K+1, n, n);
    `pattern`: the shared mask (K+1, m) or None; `sums[arch]`: the metric sums of the block
    (given the truth); `expected[arch]`: the sums of each run's exact statistics given its
    pattern (given a truth model). Sums merge across blocks (`merge`, in block order)."""

    estimates: dict[str, Estimate]
    pattern: np.ndarray | None
    sums: dict[str, Any] | None = None  # arch -> core.metrics.MetricsAccumulator
    expected: dict[str, Any] | None = None  # arch -> core.exact.ConditionalExpected


def estimate_block(
    system: System,
    archs: Sequence[str],
    z: np.ndarray,
    *,
    R: np.ndarray | None = None,
    times: np.ndarray | None = None,
    truth: np.ndarray | None = None,
    expected_of: System | None = None,
    cache: PlanCache | None = None,
    workspace: Any = None,
    keep: bool = True,
    run_offset: int = 0,
    arrivals: np.ndarray | None = None,
) -> Block:
    """Estimate a block of runs with each architecture in `archs`.

    z (runs, K+1, m): the stacked measurements of eq. (30), NaN where missing; R (K+1, m, m):
    the noise covariance of each instant (default the system's); times (K+1,): the instants
    in seconds (default k dt). `cache` (a `PlanCache` of this system, times and R) keeps the
    plans across blocks; without one they are compiled for this block.

    Given the truth x (runs, K+1, n), `sums` holds the block's metric sums (MSE, NEES, DM,
    eqs. 44-47; `workspace` is a `MetricsWorkspace` for their scratch arrays, which the sums
    do not keep); given `expected_of` (the true model, as the filters see its sensors), each
    run's exact statistics conditional on its measurement pattern (eq. 35's joint covariance
    propagated through the plan, `core.exact.analyse`), summed. `keep=False` drops the
    estimates once reduced (only the sums leave a worker).

    A nonlinear system (`System.linear` false) has no plans: its architectures run with EKF or
    UKF local filters (`core.nonlinear`), every run with its own covariances, and there is no
    exact analysis (`expected` None); `run_offset` (the block's first run) names runs in its
    errors. `arrivals` (runs, K+1, S): when the block's readings arrived, where delays differ
    per run (default: the cache's of these runs, `PlanCache.arrivals`).
    """
    if cache is None:
        cache = PlanCache.of(system, times, R, steps=z.shape[1] - 1)
    if not cache.system.linear:  # EKF/UKF: no plans, every run has its own linearisation
        cache.patterns.append(None)  # the estimates' provenance: per run
        arr = cache.block_arrivals(run_offset, z.shape[0]) if arrivals is None else arrivals
        lanes = (
            (
                a,
                nonlinear_estimate(
                    cache.system, a, z, cache.times, run_offset=run_offset, arrival=arr
                ),
            )
            for a in archs
        )  # one architecture at a time: reduced before the next is computed
        return _reduced(
            ((a, Estimate(t.mean, t.cov)) for a, t in lanes), None, truth, workspace, keep
        )
    fast = None
    late = cache.late
    if cache.one_run and expected_of is None and late is None and not reference_paths():
        from fusionlog.core.architectures.replay import replay_estimates  # a replay's path

        fast = replay_estimates(cache.system, archs, z, cache.criterion)
    elif cache.one_run and expected_of is None and not reference_paths():
        from fusionlog.core.latency_replay import late_replay_estimates  # late readings

        arr = cache.block_arrivals(run_offset, z.shape[0]) if arrivals is None else arrivals
        fast = late_replay_estimates(late, archs, z, arr if late.per_run else None, cache.criterion)
    if fast is not None:  # one run, no exact analysis: no plans
        pattern = shared_pattern(z)
        if late is not None and late.per_run:  # as the plans record it: per run
            pattern = None
        cache.patterns.append(None if pattern is None else np.packbits(pattern).tobytes())
        results = fast
    else:
        plans, pattern = cache.block_plans(archs, z, run_offset, arrivals)
        results = {a: run_plan(plan, z) for a, plan in plans.items()}
    block = _reduced(results.items(), pattern, truth, workspace, keep)
    if expected_of is not None:
        block.expected = conditional_sums(plans, expected_of, z.shape[0])
    return block


def _reduced(results: Iterable[tuple[str, Estimate]], pattern, truth, workspace, keep) -> Block:
    """The block of the architectures' `results`: their estimates (`keep`) and, given the
    truth, their metric sums (`workspace`: the caller's scratch arrays, not kept)."""
    estimates: dict[str, Estimate] = {}
    sums: dict[str, Any] | None = None
    if truth is not None:
        from fusionlog.core.metrics import MetricsAccumulator, MetricsWorkspace  # scipy: lazily

        sums = {}
        detached = MetricsWorkspace()
    for a, e in results:
        if keep:
            estimates[a] = e
        if sums is not None:
            acc = MetricsAccumulator(truth.shape[1], truth.shape[2], workspace=workspace)
            acc.add(truth, e.mean, e.cov)
            acc.workspace = detached  # the scratch arrays stay with the caller
            sums[a] = acc
    return Block(estimates, pattern, sums)


def conditional_sums(plans: dict[str, Plan], truth: System, runs: int) -> dict[str, Any]:
    """Each run's exact statistics given its pattern, summed per architecture
    (`core.exact.ConditionalExpected`): a plan shared by the block's `runs` runs is analysed
    once and counted `runs` times."""
    out = {}
    for a, plan in plans.items():
        ce = ConditionalExpected(len(plan.steps), truth.n)
        ce.add(analyse(plan, truth), 1 if plan.per_run else runs)
        out[a] = ce
    return out
