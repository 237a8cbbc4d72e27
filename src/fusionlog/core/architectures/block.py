"""The file-free estimation core: one block of runs through the architectures.

`estimate_block` is the one function that estimates a block: every caller (the estimate and
run stages, the sweep's and `run --workers`' Dask tasks, the Python API) hands it arrays --
the stacked measurements z (runs, K+1, m) of eq. (30) with NaN where a component is missing
-- and gets back each architecture's estimates and, given the truth, the block's mergeable
metric sums (`core.metrics.MetricsAccumulator`, eqs. 44-47) and, given a truth model, the
exact statistics of each run conditional on its measurement pattern
(`core.exact.ConditionalExpected`).

Plans depend on the model and on which measurements are present, never on their values. A
`PlanCache` keeps them per (architecture, pattern shared by a block's runs), so the blocks of a
log with one pattern (usually: everything present) compile each architecture once; blocks
whose runs differ (dropouts) get per-run plans built from their own masks. The cache also
records the blocks' patterns, which the estimates' provenance states (`provenance`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..model import System
from .executor import run_plan
from .plan import Estimate, Plan
from .registry import build_plan

__all__ = [
    "Block",
    "PlanCache",
    "conditional_sums",
    "estimate",
    "estimate_block",
    "keep_block_plans",
    "shared_pattern",
]

#: Inside `keep_block_plans`: the per-run plans of the last block, {(block key, arch): plan}.
_KEPT: dict[tuple[bytes, str], Plan] | None = None


@contextmanager
def keep_block_plans() -> Iterator[None]:
    """Within it, the per-run plans of the last block of runs are kept for a later stage of
    the same command on the same block: `fusionlog run` estimates, then the evaluation's exact
    analysis takes the same plans (the same model, horizon and masks) instead of building them
    again. One block's plans at most are kept (a log of several blocks: the last one's, which
    the evaluation's first block does not match), and none after it."""
    global _KEPT
    _KEPT = {}
    try:
        yield
    finally:
        _KEPT = None


def _block_key(cache: PlanCache, present: np.ndarray) -> bytes:
    """What a block's per-run plans are made of: the model, horizon, criterion and masks."""
    from .registry import NODES_AT_MOST  # the grouping's setting: a benchmark may change it

    h = hashlib.sha256(pickle.dumps((cache.system, cache.steps, cache.criterion, NODES_AT_MOST)))
    h.update(repr(present.shape).encode())
    h.update(np.packbits(present).tobytes())
    return h.digest()


def shared_pattern(z: np.ndarray) -> np.ndarray | None:
    """The (K+1, m) mask of present measurements when every run of z (M, K+1, m) has the same
    one, else None.

    A pattern shared by all runs (a sensor at half rate, a gap in every run) keeps the
    shared-gain path: one plan built with that mask serves all runs. The usual case, nothing
    missing, is answered by one pass over z (comparing every run's mask with the first costs
    seven times that).
    """
    missing = np.isnan(z)
    if not missing.any():
        return np.ones(z.shape[1:], dtype=bool)
    present = ~missing
    return present[0] if (present == present[:1]).all() else None


@dataclass
class PlanCache:
    """The plans of one system over one horizon, per (architecture, shared pattern).

    `system` is the filters' model on the log's instants, with its per-instant R where the
    noise varies (`of`); `steps` is K (instants k = 0..K).
    """

    system: System
    steps: int
    criterion: str = "trace"
    plans: dict[tuple[str, bytes], Plan] = field(default_factory=dict, repr=False)
    #: the instants (K+1,) in seconds, where they are not k dt (a nonlinear model's filters
    #: take each interval from them; the plans have them in `system` already)
    times: np.ndarray | None = field(default=None, repr=False)
    #: each block's shared pattern (`np.packbits` of the mask; None: the block's runs differed)
    patterns: list[bytes | None] = field(default_factory=list, repr=False)
    #: the cache serves a log of one run (a replay): its block is estimated without plans
    #: where that applies (`replay.replay_estimates`), the same estimates to rounding
    one_run: bool = False

    @classmethod
    def of(
        cls,
        system: System,
        times: np.ndarray | None = None,
        R: np.ndarray | None = None,
        steps: int | None = None,
    ) -> PlanCache:
        """A cache for `system` on the instants `times` (K+1,) in seconds (default k dt; see
        `System.on_times`) with the stacked noise covariance R (K+1, m, m) of each instant
        (default the system's, `System.R_at`)."""
        if times is not None:
            system = system.on_times(times)
            steps = len(times) - 1
        if R is not None:
            system = dataclasses.replace(system, Rs=np.asarray(R, dtype=float))
        if steps is None:
            raise ValueError("give the instants (times) or the number of steps")
        return cls(system, steps, times=None if times is None else np.asarray(times, float))

    def plan(self, arch: str, pattern: np.ndarray | None = None) -> Plan:
        """The plan of `arch` for a mask (K+1, m) shared by all runs (None: all present),
        compiled once."""
        K1 = self.steps + 1
        if pattern is None:
            pattern = np.ones((K1, self.system.m), dtype=bool)
        key = (arch, np.packbits(pattern).tobytes())
        plan = self.plans.get(key)
        if plan is None:
            mask = None if pattern.all() else pattern
            plan = self.plans[key] = build_plan(self.system, arch, self.steps, mask, self.criterion)
        return plan

    def block_plans(
        self, archs: Sequence[str], z: np.ndarray
    ) -> tuple[dict[str, Plan], np.ndarray | None]:
        """Each architecture's plan for the block z (runs, K+1, m) and its shared pattern (None
        when the runs differ: plans built per run, on history nodes, which the estimates and
        the exact analysis both take); the pattern is recorded for `provenance`."""
        pattern = shared_pattern(z)
        self.patterns.append(None if pattern is None else np.packbits(pattern).tobytes())
        if pattern is not None:
            return {a: self.plan(a, pattern) for a in archs}, pattern
        present = ~np.isnan(z)
        kept, key = _KEPT, b""
        if kept is not None:
            key = _block_key(self, present)
            if any(k != key for k, _ in kept):  # another block: its plans go
                kept.clear()
        plans = {}
        for a in archs:
            plan = None if kept is None else kept.get((key, a))
            if plan is None:
                plan = build_plan(
                    self.system, a, self.steps, present, self.criterion, history_nodes=True
                )
                if kept is not None:
                    kept[key, a] = plan
            plans[a] = plan
        return plans, None

    def provenance(self) -> dict[str, str]:
        """The estimates' ``measurement_pattern`` (DESIGN.md "MCAP files"): "complete", the
        mask shared by every run of every block as JSON, or "per-run" (a block's runs differed,
        two blocks differed, or there was no block)."""
        return pattern_record(self.patterns, (self.steps + 1, self.system.m))


def pattern_record(patterns: Sequence[bytes | None], shape: tuple[int, int]) -> dict[str, str]:
    """``measurement_pattern`` from blocks' shared patterns (`np.packbits` of each (K+1, m)
    mask of `shape`, None where a block's runs differed): "per-run" when any block's runs
    differed, two blocks differed or there was none; else "complete" or the mask as JSON."""
    if not patterns or any(p is None for p in patterns) or len(set(patterns)) > 1:
        return {"measurement_pattern": "per-run"}
    first = patterns[0]
    assert first is not None
    mask = np.unpackbits(np.frombuffer(first, dtype=np.uint8))[: shape[0] * shape[1]]
    mask = mask.reshape(shape).astype(bool)
    if mask.all():
        return {"measurement_pattern": "complete"}
    return {"measurement_pattern": json.dumps(mask.astype(int).tolist())}


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
    errors.
    """
    if cache is None:
        cache = PlanCache.of(system, times, R, steps=z.shape[1] - 1)
    if not cache.system.linear:  # EKF/UKF: no plans, every run has its own linearisation
        from ..nonlinear.block import nonlinear_block

        cache.patterns.append(None)  # the estimates' provenance: per run
        return nonlinear_block(cache, archs, z, truth, workspace, keep, run_offset)
    from ..reference import reference_paths

    fast = None
    if cache.one_run and expected_of is None and not reference_paths():
        from .replay import replay_estimates

        fast = replay_estimates(cache.system, archs, z, cache.criterion)
    if fast is not None:  # one run, no exact analysis: no plans
        pattern = shared_pattern(z)
        cache.patterns.append(np.packbits(pattern).tobytes())
        results = fast
    else:
        plans, pattern = cache.block_plans(archs, z)
        results = {a: run_plan(plan, z) for a, plan in plans.items()}
    runs = z.shape[0]
    estimates: dict[str, Estimate] = {}
    sums: dict[str, Any] | None = None
    if truth is not None:
        from ..metrics import MetricsAccumulator, MetricsWorkspace  # scipy: on first use only

        sums = {}
        detached = MetricsWorkspace()
    for a, e in results.items():
        if keep:
            estimates[a] = e
        if sums is not None:
            acc = MetricsAccumulator(truth.shape[1], truth.shape[2], workspace=workspace)
            acc.add(truth, e.mean, e.cov)
            acc.workspace = detached  # the scratch arrays stay with the caller
            sums[a] = acc
    expected = None
    if expected_of is not None:
        expected = conditional_sums(plans, expected_of, runs)
    return Block(estimates, pattern, sums, expected)


def conditional_sums(plans: dict[str, Plan], truth: System, runs: int) -> dict[str, Any]:
    """Each run's exact statistics given its pattern, summed per architecture
    (`core.exact.ConditionalExpected`): a plan shared by the block's `runs` runs is analysed
    once and counted `runs` times."""
    from ..exact import ConditionalExpected, analyse

    out = {}
    for a, plan in plans.items():
        ce = ConditionalExpected(len(plan.steps), truth.n)
        ce.add(analyse(plan, truth), 1 if plan.per_run else runs)
        out[a] = ce
    return out


def estimate(system: System, z: np.ndarray, arch: str, criterion: str = "trace") -> Estimate:
    """Run architecture `arch` on measurements z (M, K+1, m) (NaN: missing): `estimate_block`
    of one architecture without a cache."""
    cache = PlanCache(system, z.shape[1] - 1, criterion, one_run=z.shape[0] == 1)
    return estimate_block(system, [arch], z, cache=cache).estimates[arch]
