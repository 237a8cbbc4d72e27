"""The state kind's evaluator: its parts (`.parts.Part`) fed block by block, then an
`Evaluation`.

Which parts an evaluation has follows from what it evaluates: the Monte Carlo metrics and the
sample runs always; the exact analysis where the model is linear and the truth has the
filter's sensors (`exact_setup`); NIS and availability where the sensors log says when each
sensor measured; the PCRB for a nonlinear truth; the plane view when the scenario asks for it.
Nothing here reads or writes a file: the stages hand it arrays (`add`) or other processes' sums
(`merge`), and write what `evaluation` returns (`io.rrd.write_evaluation`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fusionlog.core.evaluation import Evaluation
from fusionlog.core.late_policy import is_late
from fusionlog.core.model import System
from fusionlog.core.names import known_arch
from fusionlog.driver import KeptPlans, PlanCache
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap.topics import estimates_topic, sensor_topic
from fusionlog.scenario import Scenario

from ..common import block_runs
from ..hooks import Array, Evaluator, Readings, Topics
from .bound_part import BoundPart
from .exact_part import ExactPart, exact_setup
from .metrics_part import MetricsPart
from .nis_part import NisPart
from .parts import Block, Elsewhere, Finished, Part
from .pcrb_part import PcrbPart
from .trajectory_part import TrajectoryPart
from .views_part import PlanePart, SamplesPart

__all__ = ["SensorLog", "StateEvaluator"]


@dataclass(frozen=True)
class SensorLog:
    """What an evaluation knows of the sensors log besides its arrays: whether it has the
    truth, and each sensor's scheduled instants where it has them (availability): (K+1,) bool
    or its bits (`io.mcap.layout.StepMask`), either sliced `[k0:k1]`."""

    has_truth: bool = True
    scheduled: dict[str, Any] | None = None
    #: a replay's truth: {"states": [names], "matched": N, "unmatched": N} (instants with and
    #: without a truth sample); its states may be some of the state's (partial truth)
    truth: dict[str, Any] | None = None
    #: when each reading arrived, (runs, K+1, S) s, where the delays differ per run
    arrivals: np.ndarray | None = None
    #: a long one-run log (`time_windows`): the sensors file, read block by block, and what
    #: reads `arrivals` for the whole run's path, on its first block
    sensors: Any = None
    load_arrivals: Any = None


class StateEvaluator(Evaluator):
    """MSE, NEES, DM per architecture with exact expected values; NIS; PCRB; sample runs;
    state plane.

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
        kept: KeptPlans | None = None,
    ) -> None:
        if filter_sys.n != truth_sys.n:
            raise FusionlogError(
                f"{source}: estimates of {filter_sys.n} states, the truth has {truth_sys.n}"
            )
        self.archs = list(archs)
        self.topics = [estimates_topic(a) for a in self.archs]
        self.sc, self.prov, self.source = sc, prov, source
        self.n = truth_sys.n
        self.sensors = tuple(s.name for s in filter_sys.sensors)  # the filters' (NIS rows)
        self.times = np.asarray(times, dtype=float)
        self.K, self.M = len(self.times) - 1, runs
        log = log or SensorLog()
        self.has_truth = log.has_truth
        recorded = sc.replay is not None
        plans = PlanCache(filter_sys, self.K, kept=kept, clock=self.times)
        plans.arrivals = log.arrivals
        self._load_arrivals, self._sensors_file = log.load_arrivals, log.sensors
        #: the policy for late measurements where some sensor is late (summary.json "late")
        self.late = filter_sys.late if is_late(filter_sys) else None
        known = [a for a in self.archs if known_arch(a, filter_sys)]
        names = list(sc.state_names)
        truthed = (
            [names.index(x) for x in log.truth["states"]] if log.truth else list(range(self.n))
        )
        self.metrics = MetricsPart(
            self.archs, self.n, self.K + 1, runs, truthed, log.has_truth, recorded,
            sc.confidence, log.truth,
        )  # fmt: skip
        parts: list[Part] = [self.metrics]
        # the readings the parts read: the filter's sensors (the truth's for a PCRB: the same
        # sensors, by the truth's names)
        pcrb = None if truth_sys.linear else PcrbPart(truth_sys, self.times)
        sensor_topics = pcrb.topics if pcrb else [sensor_topic(s.name) for s in filter_sys.sensors]
        setup = exact_setup(prov, filter_sys, truth_sys)
        if setup is not None:
            parts.append(
                ExactPart(plans, known, setup, runs, recorded, sensor_topics, log.has_truth)
            )
        # does the reported covariance bound the error: exact where the analysis is, else
        # Monte Carlo (DESIGN.md "Unknown correlation and the bound check")
        exact = known if setup is not None else []
        guessed = [a for a in self.archs if a not in exact] if log.has_truth and runs > 1 else []
        parts.append(BoundPart(exact, guessed, self.n, self.K + 1, sc.confidence))
        if pcrb is not None:  # nonlinear: the posterior Cramer-Rao bound
            parts.append(pcrb)
        if log.scheduled:  # the readings say when each sensor measured (and, replayed, NIS)
            parts.append(
                NisPart(filter_sys, known, self.K + 1, runs, log.scheduled, recorded,
                        sensor_topics, sc.confidence)
            )  # fmt: skip
        parts.append(SamplesPart(self.archs, min(sc.sample_runs, runs)))
        traj = TrajectoryPart.of(sc, self.archs, self.times, log.has_truth, source)
        if traj is not None:  # APE/RPE after the alignment (DESIGN.md "Trajectory metrics")
            parts.append(traj)
        if sc.plane_view:
            parts.append(PlanePart(self.archs, plans, sc.confidence))
        self.parts = parts
        #: the sensor topics some part needs the readings of
        self.sensor_topics = sensor_topics if any(p.topics for p in parts) else []

    def block_runs(self, requested: int | None) -> int:
        return block_runs(self.K, self.M, requested)

    def add(self, off: int, truth: Array, estimates: Topics, sensors: Readings = None) -> None:
        if self._load_arrivals is not None:  # the whole run's path: the log's arrivals
            exact = next((p for p in self.parts if isinstance(p, ExactPart)), None)
            if exact is not None:
                exact.plans.arrivals = self._load_arrivals()
            self._load_arrivals = None
        n = self.n
        runs = next(iter(estimates.values()))[0].shape[0]
        # no truth: NaN everywhere, one value broadcast (a long log's would be 32 MB per 10^6
        # instants, kept by the first run's sample until the recording is written)
        x = truth if truth is not None else np.broadcast_to(np.nan, (runs, self.K + 1, n))
        if x.shape[-1] != n:
            raise FusionlogError(f"/truth has {x.shape[-1]} values per run, not {n}")
        by_arch = {}
        for a, t in zip(self.archs, self.topics, strict=True):
            mean, cov = estimates[t]
            if mean.shape[-1] != n:
                raise FusionlogError(
                    f"{t}: estimates of {mean.shape[-1]} states, the truth has {n}"
                )
            by_arch[a] = (mean, cov)
        block = Block(off, x, truth is not None, by_arch, sensors)
        for part in self.parts:
            part.add(block)

    def merge(
        self,
        sums: dict[str, Any],
        expected: dict[str, Any] | None = None,
        trajectory: dict[str, Any] | None = None,
    ) -> None:
        """Add metric sums accumulated elsewhere (`estimate_block`'s, of runs not `add`ed
        here) and, for per-run patterns, those runs' conditional exact sums (and their
        trajectory sums)."""
        self._merge(Elsewhere(sums=sums, expected=expected or {}, trajectory=trajectory or {}))

    def add_bound(self, truth: np.ndarray, sensors: dict[str, np.ndarray]) -> None:
        """Runs whose metric sums were merged (`merge`): their truth and sensor readings, for
        what needs no estimate, the PCRB of a nonlinear model (nothing otherwise)."""
        self._merge(Elsewhere(readings=(truth, sensors)))

    def _merge(self, other: Elsewhere) -> None:
        for part in self.parts:
            part.merge(other)

    def summary(self) -> dict[str, Any]:
        """The summary.json dict (also `evaluation().summary`)."""
        return self._finish().summary

    def _head(self) -> dict[str, Any]:
        sc = self.sc
        return {
            "scenario": sc.name,
            "seed": sc.seed,
            "runs": self.M,
            "steps": self.K,
            "state_names": list(sc.state_names),
            "confidence": sc.confidence,
        }

    def time_windows(self) -> Any:
        """A `LongEvaluator` for a one-run log longer than a block of time whose evaluation
        needs nothing of the whole log at once (the Monte Carlo metrics with truth for every
        state or none, the exact analysis and the NIS of a steady model, the sample run);
        None otherwise."""
        from fusionlog.core.reference import reference_paths
        from fusionlog.driver.long_log import time_block

        if self.M != 1 or self.K + 1 <= time_block() or reference_paths():
            return None
        parts = {MetricsPart, ExactPart, SamplesPart, NisPart, BoundPart, PcrbPart, TrajectoryPart}
        parts |= {PlanePart}
        if not {type(p) for p in self.parts} <= parts:
            return None
        if any(isinstance(p, BoundPart) and p.sums for p in self.parts):
            return None  # a Monte Carlo bound (of several runs)
        return self._long(
            next((p for p in self.parts if isinstance(p, ExactPart)), None),
            next((p for p in self.parts if isinstance(p, NisPart)), None),
        )

    def _long(self, exact: ExactPart | None, nis: NisPart | None) -> Any:
        from fusionlog.core.architectures.long_log import converged, steady_log

        from .long_evaluator import LongEvaluator, LongSetup
        from .long_nis import LongNis

        log, expected, replayed = None, {}, None
        if exact is not None and self.has_truth:
            if exact.route == "per-run" and self.late is None:
                return None
            p = exact.plans
            steady = exact.route != "per-run" and exact.mask is None and p.system.time_invariant
            log = self._steady_log(p, exact.known) if steady else None
            for a in exact.known if log is not None else ():
                expected[a] = log.expected(a, exact.truth)
                rtol = self._analysis_rtol(exact.truth, log, expected[a])
                if not log.whole and not converged(expected[a], log.c, rtol):
                    log, expected = None, {}
                    break
            if log is None and self.late is not None:  # no late plans stand for it
                replayed = self._late_exact(exact)  # the stacked filters carried, else whole
                if replayed is None:
                    return None
            elif log is None:  # a recorded replay: the one-log route in blocks, else the whole
                replayed = self._replay_exact(exact)
                if replayed is None:
                    return None
        long_nis = None
        if nis is not None:
            from fusionlog.core.architectures import definition

            from ..consistency import _centralised

            forward, ckf = None, _centralised()
            if any(definition(a).locals == "smoother" for a in nis.archs):
                forward = steady_log(nis.system, [ckf], self.K)
                if forward is None and ckf in nis.archs:  # a replay: the CKF's own estimates
                    forward = ckf
                if forward is None:  # a replay without the CKF: its CKF carried block to block
                    from fusionlog.core.architectures.replay_blocks import ReplayBlocks
                    from fusionlog.driver.long_log import time_block

                    forward = ReplayBlocks.of(nis.system, [ckf], self.K, time_block())
                if forward is None:
                    return None
            long_nis = LongNis(nis, forward, ckf)
        pcrb = next((p for p in self.parts if isinstance(p, PcrbPart)), None)
        traj = next((p for p in self.parts if isinstance(p, TrajectoryPart)), None)
        plane = next((p for p in self.parts if isinstance(p, PlanePart)), None)
        inputs = None
        if plane is not None:  # the inputs' ellipses: each sensor's SKF's short plans
            p = plane.plans
            skf = [f"SKF:{s.name}" for s in p.system.sensors]
            inputs = self._steady_log(p, skf)
            if inputs is None:
                return None
        sc = self.sc
        return LongEvaluator(
            LongSetup(
                head=self._head(), archs=self.archs, topics=self.topics, times=self.times,
                n=self.n, confidence=sc.confidence, samples=min(sc.sample_runs, 1),
                full_resolution=sc.full_resolution, has_truth=self.has_truth,
                recorded=sc.replay is not None, truth_info=self.metrics.truth_info, log=log,
                expected=expected, nis=long_nis, pcrb=pcrb, trajectory=traj,
                plane=(plane, inputs) if plane is not None else None,
                replay_exact=replayed, late=self.late,
                truthed=None if len(self.metrics.truthed) == self.n else self.metrics.truthed,
                fields={
                    "state_names": tuple(sc.state_names), "confidence": sc.confidence,
                    "properties": {"scenario": sc.source, "provenance": self.prov},
                    "sensors": self.sensors, "full_resolution": sc.full_resolution,
                },
            )
        )  # fmt: skip

    def _late_exact(self, exact: ExactPart) -> Any:
        """The exact values of a long log with late sensors whose late plans of a short
        horizon do not stand for it (delays drawn or recorded, readings missing): the stacked
        filters' error covariances block by block (`.long_late`; retrodicted, the moments
        of each block's plans, `core.retrodict_blocks`; each message's own R read per block),
        where the truth is the filters' model and the path takes every architecture; else
        None. Without an exact analysis (a truth whose model is nonlinear, or whose sensors
        are not the filters') the metrics, NIS and trajectory parts read only the estimates
        and readings, block by block as an on-time log's."""
        from fusionlog.core.exact_replay import truth_is_model
        from fusionlog.core.latency_blocks import LateBlocks
        from fusionlog.core.retrodict_blocks import RetroBlocks
        from fusionlog.driver.long_log import time_block

        from .long_late import LongLateExact

        p, T = exact.plans, time_block()
        if self._sensors_file is None or not truth_is_model(p.system, exact.truth, self.K):
            return None
        kind = RetroBlocks if p.system.late == "retrodict" else LateBlocks
        blocks = kind.of(p.system, exact.known, self.K, self.times, T, p.criterion)
        if blocks is None:
            return None
        topics = [sensor_topic(s.name) for s in p.system.sensors]
        return LongLateExact(blocks, self._sensors_file, topics, exact.route == "per-run", T)

    def _steady_log(self, plans: PlanCache, archs: Sequence[str]) -> Any:
        """The short plans standing for the log (`long_log.steady_log`; with late sensors
        their late plans, `latency_long.late_steady_log`), or None."""
        from fusionlog.core.architectures.long_log import steady_log
        from fusionlog.core.latency_long import late_steady_log

        if self.late is not None:
            return late_steady_log(plans.system, archs, self.K, plans.criterion, self.times)
        return steady_log(plans.system, archs, self.K, plans.criterion)

    def _analysis_rtol(self, truth: System, log: Any, ex: Any) -> float:
        """How closely the short plans' analysis must repeat at their middle: 1e-9, with late
        sensors their analysis's own rounding (`latency_long.analysis_rtol`)."""
        if self.late is None:
            return 1e-9
        from fusionlog.core.latency_long import analysis_rtol

        return analysis_rtol(truth, log, float(np.abs(ex.mse[log.c]).max()))

    def _replay_exact(self, exact: ExactPart) -> Any:
        """The exact values of one log in blocks of time (`.long_exact`) without steady plans (a
        recorded replay, or a simulated run with dropouts or irregular instants): the one-log
        route, where the truth is the filters' model and the replay path takes them (for a
        simulated run the same values as the plans of its pattern, to rounding: the plans
        would hold every instant's maps), and where the truth is not the model (`--model`, a
        `[truth]`) its joint moments with the filters' carried (`core.exact_mismatch`);
        None otherwise."""
        from fusionlog.core.exact_replay import replay_expected_blocks
        from fusionlog.driver.long_log import time_block

        if exact.route not in ("one-log", "plans"):
            return None
        p, T = exact.plans, time_block()
        got = replay_expected_blocks(p.system, exact.truth, exact.known, self.K, T, p.criterion)
        return None if got is None else self._long_exact(got, exact.mask, p.system.m, T)

    @staticmethod
    def _long_exact(got: Any, mask: Any, m: int, T: int) -> Any:
        """The stage's blocks of `got`: the truth the model (`exact_replay.ExpectedBlocks`)
        or not (`exact_mismatch.MismatchBlocks`, FBS's spool its own)."""
        from fusionlog.core.exact_mismatch import MismatchBlocks

        from .long_exact import LongReplayExact
        from .long_mismatch import LongMismatchExact

        kind = LongMismatchExact if isinstance(got, MismatchBlocks) else LongReplayExact
        return kind(got, mask, m, T)

    def _finish(self) -> Finished:
        archs: dict[str, dict[str, Any]] = {}
        summary = {**self._head(), "architectures": archs}
        if self.late is not None:
            summary["late"] = self.late
        into = Finished(summary, archs, metric_runs=self.metrics.runs_of())
        into.fields.update(
            plane=None, availability={}, measured={}, nis=None, innovations=None, pcrb=None
        )
        # the exact values first: the metrics' summary puts them beside the Monte Carlo ones
        for part in sorted(self.parts, key=lambda p: not isinstance(p, ExactPart)):
            part.summarise(into)
        return into

    def evaluation(self, provenance: dict[str, Any] | None = None) -> Evaluation:
        """Everything accumulated, finished into an `Evaluation` (the recording's properties
        carry the scenario text and `provenance`)."""
        into = self._finish()
        return Evaluation(
            summary=into.summary,
            times=self.times,
            state_names=tuple(self.sc.state_names),
            confidence=self.sc.confidence,
            properties={"scenario": self.sc.source, "provenance": provenance or self.prov},
            sensors=self.sensors,
            full_resolution=self.sc.full_resolution,
            **into.fields,
        )
