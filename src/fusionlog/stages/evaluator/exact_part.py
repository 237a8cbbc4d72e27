"""The exact expected values beside the Monte Carlo ones (Section IV: the joint covariance of
eq. 35 propagated through each architecture's plan), by the route `core.routes.exact_route`
chooses: the plan of a shared pattern analysed once, one recorded log without plans, or for
per-run patterns (dropouts) the average of each run's exact values given its pattern, summed
block by block from the plans the block's sensor readings give (NaN = absent)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fusionlog.core.model import System
from fusionlog.core.routes import exact_route, shared_expected
from fusionlog.driver import PlanCache, conditional_sums
from fusionlog.driver.plans import PATTERN, pattern_mask

from .parts import Block, Elsewhere, Finished, Part

__all__ = ["ExactPart", "exact_setup"]


def exact_setup(prov: dict[str, str], filter_sys: System, truth_sys: System):
    """(truth model as the filter saw it, measurement mask, per run) for the exact analysis, or
    None.

    The filter stacks its sensors in its own order, so the truth is re-ordered to match by
    sensor name (a `--model` may list them differently or use only some); sensors the truth
    does not have leave no exact analysis. `per run`: the runs' patterns differ (the mask is
    then None: each block's plans are built from its sensor readings).
    """
    if truth_sys.initial is None and truth_sys.prior is None:
        return None  # a replay without [prior]: no initial distribution to propagate
    pattern = prov.get(PATTERN, "complete")
    names = [s.name for s in truth_sys.sensors]
    if any(s.name not in names for s in filter_sys.sensors):
        return None
    seen = truth_sys.subset([names.index(s.name) for s in filter_sys.sensors])
    if any(a.dim != b.dim for a, b in zip(seen.sensors, filter_sys.sensors, strict=True)):
        return None
    if not (filter_sys.linear and seen.linear):
        return None  # no exact analysis of nonlinear models
    if pattern == "per-run":
        return seen, None, True
    mask = None if pattern == "complete" else pattern_mask(pattern)
    return seen, mask, False


class ExactPart(Part):
    """The exact values of the architectures `known` (those the filter's model has), given
    `setup` (`exact_setup`, not None); `plans` the filter's plan cache on the log's instants;
    `runs` M and `recorded` (a replay) choose the route."""

    def __init__(
        self,
        plans: PlanCache,
        known: Sequence[str],
        setup: tuple[System, np.ndarray | None, bool],
        runs: int,
        recorded: bool,
        sensor_topics: Sequence[str],
        has_truth: bool = True,
    ) -> None:
        self.plans, self.known = plans, list(known)
        self.truth, self.mask, per_run = setup
        self.route = exact_route(per_run, runs, recorded)
        # per-run patterns: each run's exact values, summed block by block from its plan (the
        # estimator's, rebuilt from the sensor readings)
        self.conditional: dict[str, Any] = {}
        # without truth there is no MSE to put the exact values beside (`summarise` keeps
        # none): a replay whose late readings make its plan per run builds none here
        if self.route == "per-run" and has_truth:
            self.topics = list(sensor_topics)
            self.conditional = {a: None for a in self.known}

    def add(self, block: Block) -> None:
        if not self.conditional:
            return
        if block.sensors is None or any(t not in block.sensors for t in self.topics):
            # a block without its readings: the run average would miss its runs
            self.conditional = {}
            return
        z = np.concatenate([block.sensors[t] for t in self.topics], axis=-1)
        plans, _ = self.plans.block_plans(self.known, z, block.off)
        self._merge_expected(conditional_sums(plans, self.truth, z.shape[0]))

    def merge(self, other: Elsewhere) -> None:
        if other.expected:
            self._merge_expected(other.expected)

    def _merge_expected(self, expected: dict[str, Any]) -> None:
        for a, ce in expected.items():
            if a in self.conditional:
                own = self.conditional[a]
                self.conditional[a] = ce if own is None else own.merge(ce)

    def summarise(self, into: Finished) -> None:
        if self.route == "per-run":
            for a in self.known:
                cond = self.conditional.get(a)
                # every run the Monte Carlo metrics saw must be in the average (a caller that
                # merges accumulators from elsewhere, without their readings, leaves none)
                if cond is not None and cond.runs == into.metric_runs.get(a):
                    into.expected[a] = (cond, True)
            return
        if not into.metric_runs:  # no truth: nothing to put the exact values beside
            return
        p = self.plans
        expected = shared_expected(
            self.route,
            p.system,
            self.truth,
            self.known,
            self.mask,
            p.steps,
            p.criterion,
            lambda a: p.plan(a, self.mask),
        )
        for a in self.known:
            into.expected[a] = (expected(a), False)
