"""The Monte Carlo metrics of each architecture: MSE (eq. 45), NEES and the Mahalanobis distance
(eq. 47) summed over blocks (`core.metrics.MetricsAccumulator`), with the exact expected values
beside them, and the mean reported tr P (what a log without truth still has)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .parts import Block, Elsewhere, Finished, Part

__all__ = ["MetricsPart"]


class MetricsPart(Part):
    """`truthed`: the states the truth gives (all n, or a replay's partial truth: metrics over
    them, NEES on their marginal with as many degrees of freedom); `has_truth` False: only the
    traces (a recorded log without truth); `recorded`: a replay, whose truth may cover only
    some instants (its mean trace is of every instant's reported covariance)."""

    def __init__(
        self,
        archs: Sequence[str],
        n: int,
        instants: int,
        runs: int,
        truthed: list[int],
        has_truth: bool,
        recorded: bool,
        confidence: float,
        truth_info: dict[str, Any] | None,
    ) -> None:
        # here, not at the top: core.metrics imports scipy.special (~0.25 s), which only an
        # evaluation needs, and the stages' modules are loaded by simulate and estimate too
        from fusionlog.core.metrics import MetricsAccumulator

        self.archs, self.n, self.instants, self.M = list(archs), n, instants, runs
        self.truthed, self.has_truth, self.recorded = truthed, has_truth, recorded
        self.confidence, self.truth_info = confidence, truth_info
        self._accumulator = MetricsAccumulator
        # the truth metrics' sums (K+1 x n arrays each; none for a log without truth) and the
        # traces, made when the first block comes (`_sums`): a long log evaluated in blocks of
        # time (`StateEvaluator.time_windows`) never makes them
        self.accs: dict[str, Any] = {}
        self.trace: dict[str, np.ndarray] = {}

    def _sums(self) -> None:
        if not self.trace:
            self.trace = {a: np.zeros(self.instants) for a in self.archs}
        for a in self.archs if self.has_truth else ():
            if a not in self.accs:
                self.accs[a] = self._accumulator(self.instants, len(self.truthed))

    def add(self, block: Block) -> None:
        self._sums()
        x = block.truth
        for a in self.archs:
            mean, cov = block.estimates[a]
            tr = np.trace(cov, axis1=-2, axis2=-1)  # (K+1,) shared by all runs, or (runs, K+1)
            self.trace[a] += tr * x.shape[0] if cov.ndim == 3 else tr.sum(axis=0)
            if self.has_truth:
                self.accs[a].add(*self._marginal(x, mean, cov))

    def merge(self, other: Elsewhere) -> None:
        for a, acc in other.sums.items():
            self.accs[a] = self.accs[a].merge(acc) if a in self.accs else acc

    def runs_of(self) -> dict[str, int]:
        """The runs each architecture's metrics saw."""
        return {a: acc.runs for a, acc in self.accs.items()}

    def summarise(self, into: Finished) -> None:
        self._sums()
        series, bounds = {}, None
        for a in self.archs:
            if not self.has_truth:  # a recorded log without truth: what needs none
                into.archs[a] = {"mean_trace": self._mean_trace(a)}
                continue
            res = self.accs[a].finalize(self.confidence)
            ex, conditional = into.expected.get(a, (None, False))
            kw = (
                {"expected_mse": ex.mse_per_state, "expected_nees": ex.nees, "expected_dm": ex.dm}
                if ex is not None
                else {}
            )
            series[a], into.archs[a] = self._partial(res, kw)
            if self.recorded:
                into.archs[a]["mean_trace"] = self._mean_trace(a)
            if conditional:  # DESIGN.md "summary.json": conditional on the drawn patterns
                into.archs[a]["expected"]["conditional"] = True
            if bounds is None:
                bounds = (res.nees_lower, res.nees_upper)
        if self.truth_info is not None and self.has_truth:
            into.summary["truth"] = dict(self.truth_info)
        into.fields["series"] = series
        into.fields["nees_bounds"] = bounds
        into.fields["traces"] = (
            None if self.has_truth else {a: t / self.M for a, t in self.trace.items()}
        )

    def _mean_trace(self, a: str) -> float:
        """The mean over the instants of tr P (those with a covariance: a filter without a
        prior has none until it has seen every state), as in estimates.mcap; NaN if none."""
        tr = self.trace[a] / self.M
        tr = tr[np.isfinite(tr)]
        return float(tr.mean()) if tr.size else float("nan")

    def _marginal(self, x: np.ndarray, mean: np.ndarray, cov: np.ndarray):
        """Truth, mean and covariance of the truthed states (all of them: as given)."""
        idx = self.truthed
        if len(idx) == x.shape[-1]:
            return x, mean, cov
        return x[..., idx], mean[..., idx], cov[..., idx, :][..., :, idx]

    def _partial(self, res: Any, kw: dict[str, Any]) -> tuple[dict, dict]:
        """Series and summary of a partial truth on all n states: the untruthed states' MSE
        undefined (NaN, null in JSON); the expected MSE of the truthed states only (the exact
        NEES and DM are of the whole state, not of the marginal: left out)."""
        idx, n = self.truthed, self.n
        if len(idx) == n:
            return res.series(**kw), res.summary(**kw)
        kw = {"expected_mse": kw["expected_mse"][:, idx]} if kw else {}
        series, summary = res.series(**kw), res.summary(**kw)
        full = np.full((self.instants, n), np.nan)
        full[:, idx] = series["mse"]
        series["mse"] = full
        if "expected_mse" in series:
            e = np.full((self.instants, n), np.nan)
            e[:, idx] = series["expected_mse"]
            series["expected_mse"] = e
        per_state = [float("nan")] * n
        for j, i in enumerate(idx):
            per_state[i] = summary["mse_per_state"][j]
        summary["mse_per_state"] = per_state
        return series, summary
