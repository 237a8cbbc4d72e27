"""The state kind's evaluator: accumulates blocks of runs, then returns an `Evaluation`.

MSE (eq. 45), NEES and the Mahalanobis distance (eq. 47) are summed over blocks
(:class:`fusionlog.core.metrics.MetricsAccumulator`) and the exact expected values of the
covariance analysis (:func:`fusionlog.core.exact.analyse`) are put beside them: for a
measurement pattern shared by every run, those of its plan; for per-run patterns (dropouts),
the average of each run's exact values given its pattern (`estimate_block`'s conditional
sums, the plans built from the block's sensor readings). Nothing here reads or writes a file:
the stages hand it arrays (`add`) or other processes' sums (`merge`), and write what
`evaluation` returns (`io.rrd.write_evaluation`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusionlog.core.architectures import PlanCache, conditional_sums
from fusionlog.core.evaluation import Evaluation
from fusionlog.core.model import System
from fusionlog.core.names import known_arch
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap.topics import estimates_topic, sensor_topic
from fusionlog.scenario import Scenario

from .common import block_runs
from .kind import Array, Evaluator, Readings, Topics
from .nonlinear import PcrbPart
from .trajectory_eval import TrajectoryPart

__all__ = ["SensorLog", "StateEvaluator", "exact_setup"]

#: Sample estimates per architecture drawn in the state-plane view.
PLANE_POINTS = 300


@dataclass(frozen=True)
class SensorLog:
    """What an evaluation knows of the sensors log besides its arrays: whether it has the
    truth, and each sensor's scheduled instants (K+1,) bool where it has them (availability)."""

    has_truth: bool = True
    scheduled: dict[str, np.ndarray] | None = None
    #: a replay's truth: {"states": [names], "matched": N, "unmatched": N} (instants with and
    #: without a truth sample); its states may be some of the state's (partial truth)
    truth: dict[str, Any] | None = None


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
    pattern = prov.get("measurement_pattern", "complete")
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
    mask = None if pattern == "complete" else np.array(json.loads(pattern), dtype=bool)
    return seen, mask, False


class StateEvaluator(Evaluator):
    """MSE, NEES, DM per architecture with exact expected values; sample runs; state plane.

    `filter_sys` and `truth_sys` are on the log's instants (with any per-instant R); `runs`
    M and the instants `times` (K+1,) s are the log's; `source` names it in errors.
    """

    def __init__(
        self,
        sc: Scenario,
        archs: Sequence[str],
        filter_sys: System,
        truth_sys: System,
        runs: int,
        times: np.ndarray,
        prov: dict[str, str],
        log: SensorLog | None = None,
        source: str = "",
    ) -> None:
        # here, not at the top: core.metrics imports scipy.special (~0.25 s), which only an
        # evaluation needs, and this module is loaded by simulate and estimate too
        from fusionlog.core.metrics import MetricsAccumulator

        from .consistency import NisAccumulator

        if filter_sys.n != truth_sys.n:
            raise FusionlogError(
                f"{source}: estimates of {filter_sys.n} states, the truth has {truth_sys.n}"
            )
        self.archs = list(archs)
        self.topics = [estimates_topic(a) for a in self.archs]
        self.sc, self.prov, self.source = sc, prov, source
        self.filter_sys, self.truth_sys = filter_sys, truth_sys
        self.times = np.asarray(times, dtype=float)
        self.K, self.M = len(self.times) - 1, runs
        self.plans = PlanCache(filter_sys, self.K)
        self.known = [a for a in self.archs if known_arch(a, filter_sys)]
        self.analysable = exact_setup(prov, filter_sys, truth_sys)
        self._fast: dict[str, Any] | None = None  # one run's `exact_replay` statistics
        n = truth_sys.n
        log = log or SensorLog()
        self.truth_info = log.truth
        # the truthed states: all, or those a replay's truth gives (metrics over them, NEES on
        # their marginal with as many degrees of freedom)
        names = list(sc.state_names)
        self.truthed = (
            [names.index(x) for x in log.truth["states"]] if log.truth else list(range(n))
        )
        # the truth metrics' sums (K+1 x n arrays each): none for a log without truth
        self.accs = (
            {a: MetricsAccumulator(self.K + 1, len(self.truthed)) for a in self.archs}
            if log.has_truth
            else {}
        )
        sensor_topics = [sensor_topic(s.name) for s in filter_sys.sensors]
        self.sensor_topics: list[str] = []
        # Per-run patterns: each run's exact values, summed block by block from its plan (the
        # estimator's, rebuilt from the sensor readings: NaN = absent).
        self.conditional: dict[str, Any] = {}
        if self.analysable is not None and self.analysable[2]:
            self.sensor_topics = sensor_topics
            self.conditional = {a: None for a in self.known}
        self.has_truth = log.has_truth
        # Truth-free consistency (NIS) and each sensor's availability, from the readings: only
        # where they say something (a replayed recording: NIS; sensors with their own timing:
        # availability); the paper's scenarios keep their summaries and recordings.
        self.nis: Any = None
        self.measured: dict[str, np.ndarray] = {}
        self.scheduled = log.scheduled or {}
        self.trace = {a: np.zeros(self.K + 1) for a in self.archs}
        self.measured_points: dict[int, dict[str, np.ndarray]] = {}
        if self.scheduled:
            self.sensor_topics = sensor_topics
            if sc.replay is not None:
                self.nis = NisAccumulator(filter_sys, self.known, self.K + 1)
            self.measured = {s.name: np.zeros(self.K + 1) for s in filter_sys.sensors}
        # Nonlinear models: the posterior Cramer-Rao bound, from the truth and the readings.
        self.pcrb = None if truth_sys.linear else PcrbPart(truth_sys, self.times)
        if self.pcrb is not None:
            self.sensor_topics = self.pcrb.topics
        # APE/RPE after the alignment (DESIGN.md "Trajectory metrics"; None: no position states)
        self.trajectory = TrajectoryPart.of(sc, self.archs, self.times, log.has_truth, source)
        self.n_samples = min(sc.sample_runs, self.M)
        self.samples: dict[int, Any] = {}
        self.plane_pts: dict[str, np.ndarray] = {}
        self.plane_truth: np.ndarray | None = None
        self.plane_cov: dict[str, np.ndarray] = {}

    def block_runs(self, requested: int | None) -> int:
        return block_runs(self.K, self.M, requested)

    def add(self, off: int, truth: Array, estimates: Topics, sensors: Readings = None) -> None:
        n = self.truth_sys.n
        runs = next(iter(estimates.values()))[0].shape[0]
        # no truth: NaN everywhere, one value broadcast (a long log's would be 32 MB per 10^6
        # instants, kept by the first run's sample until the recording is written)
        x = truth if truth is not None else np.broadcast_to(np.nan, (runs, self.K + 1, n))
        if x.shape[-1] != n:
            raise FusionlogError(f"/truth has {x.shape[-1]} values per run, not {n}")
        if self.measured and sensors is not None:
            self._add_consistency(sensors, estimates)
        if self.pcrb is not None and truth is not None:
            self.pcrb.add(x, sensors)
        if self.conditional:
            if sensors is None or any(t not in sensors for t in self.sensor_topics):
                # a block without its readings: the run average would miss its runs
                self.conditional = {}
            else:
                z = np.concatenate([sensors[t] for t in self.sensor_topics], axis=-1)
                plans, _ = self.plans.block_plans(self.known, z)
                self._merge_expected(conditional_sums(plans, self.analysable[0], z.shape[0]))
        for a, t in zip(self.archs, self.topics, strict=True):
            mean, cov = estimates[t]
            if mean.shape[-1] != x.shape[-1]:
                raise FusionlogError(
                    f"{t}: estimates of {mean.shape[-1]} states, the truth has {x.shape[-1]}"
                )
            tr = np.trace(cov, axis1=-2, axis2=-1)  # (K+1,) shared by all runs, or (runs, K+1)
            self.trace[a] += tr * x.shape[0] if cov.ndim == 3 else tr.sum(axis=0)
            if self.has_truth:
                self.accs[a].add(*self._marginal(x, mean, cov))
            if self.sc.plane_view and off == 0:
                self.plane_truth = x[0]
                self.plane_pts[a] = np.moveaxis(mean[:PLANE_POINTS], 0, 1)  # (K+1, P, 2)
                self.plane_cov[a] = cov if cov.ndim == 3 else cov[0]
            for r in range(off, min(off + x.shape[0], self.n_samples)):
                c = cov if cov.ndim == 3 else cov[r - off]
                std = np.sqrt(np.clip(np.diagonal(c, axis1=-2, axis2=-1), 0, None))
                self.samples.setdefault(r, (x[r - off], {}))[1][a] = (mean[r - off], std)
        if self.trajectory is not None and truth is not None:  # the shapes checked above
            means = {a: estimates[t][0] for a, t in zip(self.archs, self.topics, strict=True)}
            self.trajectory.add(off, x, means)

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
        idx, n = self.truthed, self.truth_sys.n
        if len(idx) == n:
            return res.series(**kw), res.summary(**kw)
        kw = {"expected_mse": kw["expected_mse"][:, idx]} if kw else {}
        series, summary = res.series(**kw), res.summary(**kw)
        full = np.full((self.K + 1, n), np.nan)
        full[:, idx] = series["mse"]
        series["mse"] = full
        if "expected_mse" in series:
            e = np.full((self.K + 1, n), np.nan)
            e[:, idx] = series["expected_mse"]
            series["expected_mse"] = e
        per_state = [float("nan")] * n
        for j, i in enumerate(idx):
            per_state[i] = summary["mse_per_state"][j]
        summary["mse_per_state"] = per_state
        return series, summary

    def merge(
        self,
        sums: dict[str, Any],
        expected: dict[str, Any] | None = None,
        trajectory: dict[str, Any] | None = None,
    ) -> None:
        """Add metric sums accumulated elsewhere (`estimate_block`'s, of runs not `add`ed
        here) and, for per-run patterns, those runs' conditional exact sums (and their
        trajectory sums, `trajectory_eval.trajectory_block`)."""
        if trajectory and self.trajectory is not None:
            self.trajectory.merge(trajectory)
        for a, acc in sums.items():
            self.accs[a] = self.accs[a].merge(acc) if a in self.accs else acc
        if expected:
            self._merge_expected(expected)

    def add_bound(self, truth: np.ndarray, sensors: dict[str, np.ndarray]) -> None:
        """Runs whose metric sums were merged (`merge`): their truth and sensor readings, for
        what needs no estimate, the PCRB of a nonlinear model (nothing otherwise)."""
        if self.pcrb is not None:
            self.pcrb.add(truth, sensors)

    def _merge_expected(self, expected: dict[str, Any]) -> None:
        for a, ce in expected.items():
            if a in self.conditional:
                own = self.conditional[a]
                self.conditional[a] = ce if own is None else own.merge(ce)

    def _add_consistency(self, sensors: dict[str, np.ndarray], estimates: dict[str, Any]) -> None:
        """NIS of each architecture and the sensors' availability, for one block."""
        fs = self.filter_sys
        if self.nis is not None:
            z = np.concatenate([sensors[t] for t in self.sensor_topics], axis=-1)
            self.nis.add(z, {a: estimates[estimates_topic(a)] for a in self.nis.archs})
            if not self.measured_points:  # the first run's readings of a state, under its estimates
                H = fs.linear_measurement() if fs.linear else None
                for s, t, sl in zip(fs.sensors, self.sensor_topics, fs.sensor_slices, strict=True):
                    for row, h in enumerate(H[sl] if H is not None else ()):
                        if np.count_nonzero(h) == 1 and h.max() == 1.0:
                            state = int(np.argmax(h))
                            self.measured_points.setdefault(state, {})[s.name] = sensors[t][
                                0, :, row
                            ]
        for s, t in zip(fs.sensors, self.sensor_topics, strict=True):
            self.measured[s.name] += (~np.isnan(sensors[t]).any(axis=-1)).sum(axis=0)

    def _expected(self, a: str) -> tuple[Any, bool]:
        """The exact expected values of architecture `a` (None: there are none) and whether
        they are conditional on the drawn patterns (the run average of each run's)."""
        from fusionlog.core.exact import analyse
        from fusionlog.core.exact_replay import replay_expected

        if self.analysable is None or a not in self.known:
            return None, False
        truth_seen, mask, per_run = self.analysable
        if not per_run:
            if self._fast is None:  # a recorded log: without plans where the truth is the model
                args = (self.filter_sys, truth_seen, self.known, mask, self.K, self.plans.criterion)
                one_log = self.M == 1 and self.sc.replay is not None
                self._fast = replay_expected(*args) if one_log else {}
            if a in self._fast:
                return self._fast[a], False
            return analyse(self.plans.plan(a, mask), truth_seen), False
        cond = self.conditional.get(a)
        # every run the Monte Carlo metrics saw must be in the average (a caller that merges
        # accumulators from elsewhere, without their readings, leaves none)
        if cond is None or a not in self.accs or cond.runs != self.accs[a].runs:
            return None, False
        return cond, True

    def summary(self) -> dict[str, Any]:
        """The summary.json dict (also `evaluation().summary`)."""
        return self._finish()[0]

    def _finish(self) -> tuple[dict[str, Any], dict[str, Any], Any]:
        arch_summary, series, bounds = {}, {}, None
        nis = self.nis.summary(self.sc.confidence) if self.nis is not None else {}
        for a in self.archs:
            if not self.has_truth:  # a recorded log without truth: what needs none
                mean_trace = self._mean_trace(a)
                arch_summary[a] = {"mean_trace": mean_trace} | ({"nis": nis[a]} if a in nis else {})
                continue
            res = self.accs[a].finalize(self.sc.confidence)
            ex, conditional = self._expected(a)
            kw = (
                {"expected_mse": ex.mse_per_state, "expected_nees": ex.nees, "expected_dm": ex.dm}
                if ex is not None
                else {}
            )
            series[a], arch_summary[a] = self._partial(res, kw)
            if self.sc.replay is not None:
                # a replay's truth may cover only some instants: the mean trace is of every
                # instant's reported covariance, as in estimates.mcap
                arch_summary[a]["mean_trace"] = self._mean_trace(a)
            if self.pcrb is not None:  # no exact analysis: `expected` is null, the PCRB stands
                arch_summary[a]["expected"] = None
            if conditional:  # DESIGN.md "summary.json": conditional on the drawn patterns
                arch_summary[a]["expected"]["conditional"] = True
            if a in nis:
                arch_summary[a]["nis"] = nis[a]
            if self.trajectory is not None:
                arch_summary[a] |= self.trajectory.summary(a)
            if bounds is None:
                bounds = (res.nees_lower, res.nees_upper)
        summary = {
            "scenario": self.sc.name,
            "seed": self.sc.seed,
            "runs": self.M,
            "steps": self.K,
            "state_names": list(self.sc.state_names),
            "confidence": self.sc.confidence,
            "architectures": arch_summary,
        }
        if self.truth_info is not None and self.has_truth:
            summary["truth"] = dict(self.truth_info)
        if self.pcrb is not None:  # DESIGN.md: no exact analysis, the PCRB beside the values
            summary["pcrb"] = self.pcrb.summary()
        return summary, series, bounds

    def _plane(self) -> dict[str, Any] | None:
        if not self.sc.plane_view or self.plane_truth is None:
            return None
        from fusionlog.core.metrics import chi2_quantile  # loaded by __init__ (see there)

        inputs = {
            f"input {s.name}": self.plans.plan(f"SKF:{s.name}").reported_cov
            for s in self.filter_sys.sensors
        }
        return {
            "truth": self.plane_truth,
            "estimates": self.plane_pts,
            "ellipses": {**inputs, **self.plane_cov},
            # the ellipse of a 2-D Gaussian at the confidence: chi-square with 2 dof
            "scale": float(np.sqrt(chi2_quantile(self.sc.confidence, 2))),
        }

    def evaluation(self, provenance: dict[str, Any] | None = None) -> Evaluation:
        """Everything accumulated, finished into an `Evaluation` (the recording's properties
        carry the scenario text and `provenance`)."""
        from .consistency import availability

        summary, series, bounds = self._finish()
        return Evaluation(
            summary=summary,
            times=self.times,
            state_names=tuple(self.sc.state_names),
            confidence=self.sc.confidence,
            series=series,
            nees_bounds=bounds,
            samples=self.samples,
            plane=self._plane(),
            availability={
                name: availability(self.measured[name], self.scheduled[name], self.M)
                for name in self.measured
            },
            nis=self.nis.series(self.sc.confidence) if self.nis is not None else None,
            traces=None if self.has_truth else {a: t / self.M for a, t in self.trace.items()},
            measured=self.measured_points,
            innovations=(
                self.nis.first_run()
                if self.nis is not None and self.sc.replay is not None
                else None
            ),
            properties={"scenario": self.sc.source, "provenance": provenance or self.prov},
            pcrb=None if self.pcrb is None else self.pcrb.per_state(),
            sensors=tuple(s.name for s in self.filter_sys.sensors),
            trajectory=None if self.trajectory is None else self.trajectory.recording(),
        )
