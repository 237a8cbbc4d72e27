"""A long one-run log evaluated in blocks of time (issue 34), in memory that does not grow with
its instants.

Per block: each architecture's Monte Carlo metrics of its instants (`MetricsAccumulator` on the
block: one run's metrics at an instant need no other instant), the exact values of the same
instants (the short plans of `core.architectures.long_log`, analysed once: the shared plan's
covariances at each block's instants), the NIS and what else the readings say (`.long_nis`)
and the first run's truth and estimates; the summary sums over instants (`core.step_sums`) and
the recording's series are reduced bucket by bucket (`core.decimate`) as the blocks come, so
neither keeps a (K+1) array. `StateEvaluator.time_windows` says which evaluations go this way:
one run, truth for every state or none, no part that needs the whole log at once (PCRB,
trajectory metrics, the state plane); the others take the whole run at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fusionlog.core.architectures.long_log import SteadyLog, expected_window
from fusionlog.core.bound import bound_summary
from fusionlog.core.decimate import TreeDecimator, bucket_size, note, point_steps, with_derived
from fusionlog.core.evaluation import Evaluation
from fusionlog.core.step_sums import StepSums
from fusionlog.io.rrd.style import CKF

from .long_nis import LongNis

__all__ = ["LongEvaluator", "LongSetup"]


@dataclass
class LongSetup:
    """What a `LongEvaluator` takes of its `StateEvaluator`: the summary's first fields
    (`head`), the estimates' topics per architecture, the instants, the truth (`has_truth`:
    of every state; `recorded`: a replay, whose mean trace is of every instant, `truth_info`
    its truth record), the exact analysis (`expected[arch]` of the short plans of `log`), the
    NIS (`nis`), the `Evaluation`'s other fields."""

    head: dict[str, Any]
    archs: Sequence[str]
    topics: Sequence[str]
    times: np.ndarray
    n: int
    confidence: float
    samples: int
    full_resolution: bool
    has_truth: bool
    recorded: bool
    truth_info: dict[str, Any] | None
    log: SteadyLog | None
    expected: dict[str, Any]
    nis: LongNis | None
    fields: dict[str, Any] = field(default_factory=dict)
    #: a nonlinear truth's `PcrbPart` (its system and sensor topics), or None
    pcrb: Any = None
    #: the `TrajectoryPart` (APE/RPE, `.long_trajectory`), or None
    trajectory: Any = None
    #: the `PlanePart` and the short plans of its inputs (`.views_part.LongPlane`), or None
    plane: Any = None
    #: a recorded replay's exact values block by block (`.long_exact.LongReplayExact`)
    replay_exact: Any = None
    #: the states the truth gives where it gives only some (partial truth: metrics over them)
    truthed: list[int] | None = None
    #: the policy for late measurements where some sensor is late (summary.json "late")
    late: str | None = None

    @property
    def bound(self) -> dict[str, np.ndarray]:
        """Each exact architecture's bound ratio at the short plans' steps (`Expected.bound`)."""
        if not hasattr(self, "_bound"):
            self._bound = {a: np.asarray(ex.bound, dtype=float) for a, ex in self.expected.items()}
        return self._bound


class LongEvaluator:
    """Blocks of time in (`add`), the finished `Evaluation` out (`evaluation`)."""

    def __init__(self, setup: LongSetup) -> None:
        self.s = setup
        self.b = bucket_size(len(setup.times), setup.full_resolution)
        self.tree = TreeDecimator(self.b)
        truthed = setup.n if setup.truthed is None else len(setup.truthed)
        self.sums = {a: StepSums(truthed) for a in setup.archs}
        self.traces = {a: np.zeros(2) for a in setup.archs}  # sum and count of finite tr P
        self.pcrb = _LongPcrb(setup.pcrb, setup.times) if setup.pcrb is not None else None
        self.traj = None
        if setup.trajectory is not None:
            from .long_trajectory import LongTrajectory

            self.traj = LongTrajectory(setup.trajectory, setup.archs)
        self.plane = None
        if setup.plane is not None:
            from .views_part import LongPlane

            self.plane = LongPlane(*setup.plane, point_steps(len(setup.times), self.b))

    def add(
        self,
        k0: int,
        k1: int,
        truth: np.ndarray | None,
        estimates: dict[str, Any],
        sensors: dict[str, np.ndarray] | None = None,
    ) -> None:
        """The block of instants [k0, k1): truth (1, w, n) (None: the log has none), {topic:
        (mean (1, w, n), cov (w, n, n))}, the readings {topic: (1, w, dim)} the NIS needs."""
        from fusionlog.core.metrics import MetricsAccumulator

        s = self.s
        w = k1 - k0
        idx = s.log.index(k0, k1) if s.log is not None else None
        replayed = s.replay_exact.window(k0, k1) if s.replay_exact is not None else {}
        series, traces, bounds, sample, by_arch = {}, {}, None, {}, {}
        for a, t in zip(s.archs, s.topics, strict=True):
            mean, cov = by_arch[a] = estimates[t]
            tr = np.trace(cov, axis1=-2, axis2=-1)
            ok = np.isfinite(tr)
            self.traces[a] += (tr[ok].sum(), ok.sum())
            std = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0, None))
            sample[a] = (mean[0], std)
            if not s.has_truth:
                traces[a] = tr
                continue
            t = s.truthed
            acc = MetricsAccumulator(w, s.n if t is None else len(t))
            acc.add(*((truth, mean, cov) if t is None else _marginal(t, truth, mean, cov)))
            res = acc.finalize(s.confidence)
            kw, ratio = {}, None
            if a in s.expected:
                ex, ratio = expected_window(s.expected[a], idx), s.bound[a][idx]
            elif a in replayed:
                ex, ratio = replayed[a]
            if ratio is not None:
                kw = {"expected_mse": ex.mse_per_state, "expected_nees": ex.nees,
                      "expected_dm": ex.dm}  # fmt: skip
                if t is not None:  # the exact NEES and DM are of the whole state: left out
                    nan = np.full(w, np.nan)
                    kw = {"expected_mse": ex.mse_per_state[:, t], "expected_nees": nan,
                          "expected_dm": nan}  # fmt: skip
            if t is not None:  # (the series without the whole state's NEES and DM)
                series[a] = _whole_state(res.series(**{k: kw[k] for k in kw if "mse" in k}), t, s.n)
            else:
                series[a] = res.series(**kw)
            if ratio is not None:  # the bound check's ratio, exact (`core.bound`)
                series[a]["bound"] = ratio
            self.sums[a].add(res, **kw)
            if bounds is None:
                bounds = (res.nees_lower, res.nees_upper)
        tree: dict[str, Any] = {"series": series, "nees_bounds": bounds, "traces": traces}
        if s.samples:
            x = truth[0] if truth is not None else np.full((w, s.n), np.nan)
            tree["samples"] = {0: (x, sample)}
        if s.nis is not None and sensors is not None:
            tree.update(s.nis.add(k0, k1, sensors, by_arch))
        if self.pcrb is not None:
            tree["pcrb"] = self.pcrb.add(k0, k1, truth, sensors)
        if self.plane is not None:
            x = truth if truth is not None else np.full((1, w, s.n), np.nan)
            self.plane.add(k0, k1, x, by_arch)
        if self.traj is not None and truth is not None:
            self.traj.add(k0, k1, truth, {a: by_arch[a][0] for a in s.archs})
        self.tree.add(with_derived(tree, CKF))

    def _mean_trace(self, a: str) -> float:
        total, count = self.traces[a]
        return float(total / count) if count else float("nan")

    def evaluation(self) -> Evaluation:
        """The finished evaluation."""
        s = self.s
        archs: dict[str, dict[str, Any]] = {}
        for a in s.archs:
            if not s.has_truth:  # a recorded log without truth: what needs none
                archs[a] = {"mean_trace": self._mean_trace(a)}
                continue
            archs[a] = self.sums[a].summary()
            if s.truthed is not None:  # the untruthed states' MSE undefined (null)
                per_state = [float("nan")] * s.n
                for j, i in enumerate(s.truthed):
                    per_state[i] = archs[a]["mse_per_state"][j]
                archs[a]["mse_per_state"] = per_state
            if s.recorded:
                archs[a]["mean_trace"] = self._mean_trace(a)
        for a in s.expected:  # the bound check over every instant (`BoundPart`'s)
            b = bound_summary(s.bound[a])
            if b is not None and a in archs:
                archs[a]["bound"] = {**b, "worst_step": s.log.first_instant(b["worst_step"])}
        for a in s.replay_exact.bounds if s.replay_exact is not None else ():
            b = s.replay_exact.bound_summary(a)
            if b is not None and a in archs:
                archs[a]["bound"] = b
            if getattr(s.replay_exact, "conditional", False) and a in archs:
                archs[a]["expected"]["conditional"] = True  # on the drawn delays
        summary = {**s.head, "architectures": archs}
        if s.late is not None:
            summary["late"] = s.late
        pcrb = None
        if self.pcrb is not None:  # no exact analysis beside the Monte Carlo values
            for entry in archs.values():
                if "mse" in entry:
                    entry["expected"] = None
            summary["pcrb"] = self.pcrb.summary()
            pcrb = None if summary["pcrb"] is None else "drawn"
        if self.plane is not None:
            s.fields["plane"] = self.plane.result()
        if self.traj is not None:  # APE/RPE: the second pass over the positions
            entries, s.fields["trajectory"] = self.traj.finish(self.b)
            for a, entry in archs.items():
                if "mse" in entry:
                    entry |= entries[a]
        if s.truth_info is not None and s.has_truth:
            summary["truth"] = dict(s.truth_info)
        if s.nis is not None:
            for a, entry in s.nis.summary().items():
                archs[a]["nis"] = entry
        drawn = self.tree.result()
        K1 = len(s.times)
        steps = point_steps(K1, self.b)
        nis = drawn.get("nis") if s.nis is not None and s.nis.archs else None
        if pcrb is not None:
            s.fields["pcrb"] = drawn["pcrb"]
        return Evaluation(
            summary=summary,
            times=s.times[steps],
            series=drawn["series"],
            nees_bounds=drawn["nees_bounds"],
            samples=drawn.get("samples", {}),
            traces=None if s.has_truth else drawn["traces"],
            availability=drawn.get("availability", {}),
            measured=drawn.get("measured", {}) if nis is not None else {},
            nis=nis,
            bands=drawn.get("bands"),
            innovations=drawn.get("innovations") if nis is not None else None,
            steps=steps if self.b > 1 else None,
            decimation=note(K1, self.b) if self.b > 1 else None,
            **s.fields,
        )


class _LongPcrb:
    """The posterior Cramer-Rao bound of a long one-run log block by block (`PcrbBlocks`, the
    recursion carried): each block's diagonal for the recording, the sums over instants for
    the summary (`pcrb_summary`'s mean over instants); None where a block lacks its readings
    (as `PcrbPart`)."""

    def __init__(self, part: Any, times: np.ndarray) -> None:
        from fusionlog.core.nonlinear.pcrb import PcrbBlocks

        self.blocks = PcrbBlocks(part.acc.system, times)
        self.topics = part.topics
        self.total: np.ndarray | None = None  # per state, the sum over instants
        self.count, self.complete = 0, True

    def add(self, k0: int, k1: int, truth: np.ndarray | None, sensors: dict | None) -> np.ndarray:
        """The block's bound on each state's MSE (w, n) (NaN once the bound is unknown)."""
        if truth is None or not sensors or any(t not in sensors for t in self.topics):
            self.complete = False
        if not self.complete:
            return np.full((k1 - k0, self.blocks.system.n), np.nan)
        present = np.stack([~np.isnan(sensors[t]).any(axis=-1) for t in self.topics], axis=-1)
        diag = np.diagonal(self.blocks.add(k0, truth, present), axis1=-2, axis2=-1).copy()
        self.total = diag.sum(axis=0) + (self.total if self.total is not None else 0.0)
        self.count += len(diag)
        return diag

    def summary(self) -> dict[str, Any] | None:
        """summary.json's "pcrb" (`core.nonlinear.pcrb_summary`), None when incomplete."""
        if not self.complete or self.total is None:
            return None
        per_state = self.total / self.count
        return {
            "mse": float(per_state.sum() / len(per_state)),
            "mse_per_state": [float(v) for v in per_state],
        }


def _marginal(idx: list[int], x: np.ndarray, mean: np.ndarray, cov: np.ndarray):
    """Truth, mean and covariance of the truthed states `idx` (a partial truth, `MetricsPart`)."""
    return x[..., idx], mean[..., idx], cov[..., idx, :][..., :, idx]


def _whole_state(series: dict[str, Any], idx: list[int], n: int) -> dict[str, Any]:
    """A partial truth's series on all n states: NaN for the untruthed states' MSE."""
    for key in ("mse", "expected_mse"):
        if key in series:
            full = np.full((len(series[key]), n), np.nan)
            full[:, idx] = series[key]
            series[key] = full
    return series
