"""The bound check (DESIGN.md "Unknown correlation and the bound check"): whether each
architecture's reported covariance bounds its true error, lambda_max(P^-1 E[e e^T]) <= 1 at
every instant (`core.bound`). From the exact analysis where there is one (the exact part's
`Expected`, or per run the worst over the runs); otherwise, with the truth and at least two
runs, a Monte Carlo estimate of the same ratio summed block by block here (`BoundSums`).

summary.json: ``architectures.<A>.bound``; the recording: the series ``bound`` of each
architecture (`io.rrd`'s ``metrics/bound/<ARCH>``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fusionlog.core.bound import BoundSums, bound_summary

from .parts import Block, Elsewhere, Finished, Part

__all__ = ["BoundPart"]


class BoundPart(Part):
    """`exact`: the architectures the exact part covers (their ratio comes from it);
    `monte_carlo`: the others, estimated here from the blocks `add`ed when the truth is
    there. A run whose sums were merged from elsewhere (`--workers`) is not in those sums: the
    Monte Carlo estimate is then left out rather than made of some of the runs."""

    def __init__(
        self,
        exact: Sequence[str],
        monte_carlo: Sequence[str],
        n: int,
        instants: int,
        confidence: float,
    ) -> None:
        self.exact, self.confidence = list(exact), confidence
        self.sums = {a: BoundSums(instants, n) for a in monte_carlo}

    def add(self, block: Block) -> None:
        if not block.has_truth:
            self.sums = {}
            return
        for a, acc in self.sums.items():
            mean, cov = block.estimates[a]
            acc.add(block.truth, mean, cov)

    def merge(self, other: Elsewhere) -> None:
        if other.sums:  # runs evaluated elsewhere, whose errors are not in these sums
            for a in other.sums:
                self.sums.pop(a, None)

    def summarise(self, into: Finished) -> None:
        series = into.fields.get("series") or {}
        for a in self.exact:
            ex, _ = into.expected.get(a, (None, False))
            if ex is None or a not in into.archs:
                continue
            ratio = np.asarray(ex.bound, dtype=float)
            self._put(into, series, a, ratio, bound_summary(ratio))
        for a, acc in self.sums.items():
            if a not in into.archs or int(acc.count.max(initial=0)) < 2:
                continue
            ratio, se = acc.ratio()
            self._put(into, series, a, ratio, bound_summary(ratio, se, self.confidence))

    @staticmethod
    def _put(into: Finished, series: dict, a: str, ratio: np.ndarray, summary) -> None:
        if summary is None:
            return
        into.archs[a]["bound"] = summary
        if a in series:
            series[a]["bound"] = ratio
