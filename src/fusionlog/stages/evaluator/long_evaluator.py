"""A long one-run log evaluated in blocks of time (issue 34), in memory that does not grow with
its instants.

Per block: each architecture's Monte Carlo metrics of its instants (`MetricsAccumulator` on the
block: one run's metrics at an instant need no other instant), the exact values of the same
instants (the short plans of `core.architectures.long_log`, analysed once: the shared plan's
covariances at each block's instants), and the first run's truth and estimates; the summary
sums over instants (`core.step_sums`) and the recording's series reduced bucket by bucket
(`core.decimate`) as the blocks come, so neither keeps a (K+1) array. `StateEvaluator.
time_windows` says which evaluations go this way: one run, truth for every state, no parts
that need the whole log (NIS and its whiteness, availability, PCRB, trajectory metrics, the
state plane); the others take the whole run at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fusionlog.core.architectures.long_log import SteadyLog, expected_window
from fusionlog.core.decimate import TreeDecimator, bucket_size, note, point_steps
from fusionlog.core.evaluation import Evaluation
from fusionlog.core.step_sums import StepSums

__all__ = ["LongEvaluator"]


class LongEvaluator:
    """`head`: the summary's first fields; `expected`: each architecture's exact analysis of the
    short plans (`SteadyLog.expected`) with `log` to index it, or None."""

    def __init__(
        self,
        head: dict[str, Any],
        archs: Sequence[str],
        topics: Sequence[str],
        times: np.ndarray,
        n: int,
        confidence: float,
        samples: int,
        full_resolution: bool,
        log: SteadyLog | None,
        expected: dict[str, Any],
        fields: dict[str, Any],
    ) -> None:
        self.head, self.archs, self.topics = head, list(archs), list(topics)
        self.times, self.n, self.confidence = times, n, confidence
        self.samples, self.log, self.expected = samples, log, expected
        self.fields = fields  # the `Evaluation`'s other fields
        self.b = bucket_size(len(times), full_resolution)
        self.tree = TreeDecimator(self.b)
        self.sums = {a: StepSums(n) for a in self.archs}

    def add(self, k0: int, k1: int, truth: np.ndarray, estimates: dict[str, Any]) -> None:
        """The block of instants [k0, k1): truth (1, w, n), {topic: (mean (1, w, n), cov
        (w, n, n))}."""
        from fusionlog.core.metrics import MetricsAccumulator

        w = k1 - k0
        idx = self.log.index(k0, k1) if self.log is not None else None
        series, bounds, sample = {}, None, {}
        for a, t in zip(self.archs, self.topics, strict=True):
            mean, cov = estimates[t]
            acc = MetricsAccumulator(w, self.n)
            acc.add(truth, mean, cov)
            res = acc.finalize(self.confidence)
            kw = {}
            if a in self.expected:
                ex = expected_window(self.expected[a], idx)
                kw = {"expected_mse": ex.mse_per_state, "expected_nees": ex.nees,
                      "expected_dm": ex.dm}  # fmt: skip
            series[a] = res.series(**kw)
            self.sums[a].add(res, **kw)
            if bounds is None:
                bounds = (res.nees_lower, res.nees_upper)
            std = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0, None))
            sample[a] = (mean[0], std)
        tree = {"series": series, "nees_bounds": bounds}
        if self.samples:
            tree["samples"] = {0: (truth[0], sample)}
        self.tree.add(tree)

    def evaluation(self) -> Evaluation:
        """The finished evaluation."""
        summary = dict(self.head)
        summary["architectures"] = {a: self.sums[a].summary() for a in self.archs}
        drawn = self.tree.result()
        K1 = len(self.times)
        steps = point_steps(K1, self.b)
        return Evaluation(
            summary=summary,
            times=self.times[steps],
            series=drawn["series"],
            nees_bounds=drawn["nees_bounds"],
            samples=drawn.get("samples", {}),
            steps=steps if self.b > 1 else None,
            decimation=note(K1, self.b) if self.b > 1 else None,
            **self.fields,
        )
