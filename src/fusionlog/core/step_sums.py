"""The summary of one run's metrics from blocks of time (issue 34): sums over instants.

`metrics.MetricsAccumulator` keeps per-instant sums over runs, (K+1) arrays that a one-run log
of 10^6 instants cannot keep for seven architectures. For one run each block of time is
finalised on its own (`MetricsResult` of its instants: the per-instant values do not depend on
the other instants), and what the summary averages over the instants is summed here: eq. 45's
MSE per state, the mean trace, ANEES, eq. 47's DM, the share of instants whose NEES lies in the
chi-square band, and the exact values' finite means over the same instants (as
`MetricsResult.summary` and `expected_overall` compute them from the whole arrays).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["StepSums"]


class StepSums:
    """Sums over the valid instants (an estimate defined) of a one-run log's blocks."""

    def __init__(self, n: int) -> None:
        self.valid = 0
        self.excluded = 0
        self.inside = 0
        self.mse = np.zeros(n)
        self.trace = self.nees = self.dm = 0.0
        self.expected: dict[str, list[np.ndarray]] | None = None  # key: [sum, count]

    def add(self, res: Any, expected_mse=None, expected_nees=None, expected_dm=None) -> None:
        """One block's `MetricsResult` and its exact values (instants of the block)."""
        v = res.valid_steps
        self.valid += int(v.sum())
        self.excluded += int(res.excluded.sum())
        self.inside += int(res.nees_inside[v].sum())
        self.mse += res.mse_step[v].sum(axis=0)
        self.trace += float(res.trace_step[v].sum())
        self.nees += float(res.nees_step[v].sum())
        self.dm += float(res.dm_step[v].sum())
        if expected_mse is None:
            return
        if self.expected is None:
            n = len(self.mse)
            self.expected = {
                "mse": [np.zeros(n), np.zeros(n)],
                "anees": [np.zeros(()), np.zeros(())],
                "dm": [np.zeros(()), np.zeros(())],
            }
        for key, arr in (("mse", expected_mse), ("anees", expected_nees), ("dm", expected_dm)):
            a = np.asarray(arr, dtype=float)[v]
            ok = np.isfinite(a)
            self.expected[key][0] += np.where(ok, a, 0.0).sum(axis=0)
            self.expected[key][1] += ok.sum(axis=0)

    def summary(self) -> dict[str, Any]:
        """The architecture's summary.json entry, as `MetricsResult.summary` gives it for one
        run (its standard errors: NaN, one run has no spread of per-run averages)."""
        nan = float("nan")
        V = self.valid
        per_state = self.mse / V if V else np.full(len(self.mse), nan)
        expected: dict[str, float | None] = {"mse": None, "anees": None, "dm": None}
        if self.expected is not None:
            s, c = self.expected["mse"]
            expected["mse"] = float(np.mean(s / c)) if (c > 0).all() else None
            for key in ("anees", "dm"):
                s, c = self.expected[key]
                expected[key] = float(s / c) if c > 0 else None
        return {
            "mse": float(np.mean(per_state)) if V else nan,
            "mse_per_state": [float(x) for x in per_state],
            "mean_trace": self.trace / V if V else nan,
            "anees": self.nees / V if V else nan,
            "nees_fraction_inside": self.inside / V if V else nan,
            "dm": self.dm / V if V else nan,
            "expected": expected,
            "stderr": {"mse": nan, "anees": nan, "dm": nan},
            "excluded": self.excluded,
        }
