"""The state kind's stage hooks: linear Gaussian systems and the paper's fusion architectures.

Simulation is :func:`fusionlog.core.simulate.simulate`; estimation compiles each architecture
into a plan once per measurement pattern shared by a block's runs (:mod:`fusionlog.core.
architectures`) and falls back to the per-run path when runs differ; evaluation accumulates
MSE (eq. 45), NEES and the Mahalanobis distance (eq. 47) over blocks
(:class:`fusionlog.core.metrics.MetricsAccumulator`) and puts the exact expected values of the
covariance analysis (:func:`fusionlog.core.exact.analyse`) beside them: for a measurement pattern
shared by every run, those of its plan; for per-run patterns (dropouts), the average of each
run's exact values given its pattern (:class:`fusionlog.core.exact.ConditionalExpected`), its
plan built from the block's sensor readings.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from fusionlog.core.architectures import Plan, build_plan, estimate, run_plan, shared_pattern
from fusionlog.core.exact import ConditionalExpected, Expected, analyse
from fusionlog.core.model import System
from fusionlog.core.names import parse_arch
from fusionlog.core.simulate import simulate
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile, McapWriter
from fusionlog.scenario import Scenario, load_model, system_from_dict, system_to_dict

from .common import block_runs
from .kind import Array, Estimator, Evaluator, Kind, Model, Prov, Readings, Sens, StepWriter, Topics
from .noise import with_message_covariances
from .nonlinear import PcrbPart, step_writers

#: Sample estimates per architecture drawn in the state-plane view.
PLANE_POINTS = 300


class StateKind(Kind):
    name = "state"

    def system_fields(self, scenario: Scenario) -> dict[str, str]:
        return {"system": json.dumps(system_to_dict(scenario.system))}

    def bytes_per_run_step(self, scenario: Scenario) -> int:
        # truth and measurements in float64, and the plans' per-step maps of the estimate stage
        s: System = scenario.system
        return 8 * (s.n + s.m) * 4 + 8 * s.n * (s.n + s.m) * len(scenario.architectures)

    def sensor_names(self, system: System) -> list[str]:
        return [s.name for s in system.sensors]

    def check_architectures(self, names: Sequence[str], system: System, where: str) -> list[str]:
        for a in names:
            try:
                parse_arch(a, [s.name for s in system.sensors])
            except ValueError as e:
                raise FusionlogError(f"{where}: {e}") from e
        return list(dict.fromkeys(names))

    def simulate(
        self, scenario: Scenario, run_offset: int, runs: int
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        sched = scenario.schedule
        system = scenario.system.on_times(sched.times)
        measures = None if sched.measures.all() else sched.measures
        x, z = simulate(system, sched.steps, scenario.seed, run_offset, runs, measures)
        return x, [z[..., sl] for sl in system.sensor_slices]

    def model(self, sensors: McapFile, recorded: Scenario | None, model_path: Path | None) -> Model:
        if model_path is None:
            recorded = self.recorded(sensors, recorded)
            system, source = recorded.system, "scenario"
        else:
            system, source = load_model(model_path, "state"), str(model_path)
            if recorded is not None and system.n != recorded.system.n:
                raise FusionlogError(
                    f"{model_path}: the model has {system.n} states, "
                    f"the scenario recorded in {sensors.path} has {recorded.system.n}"
                )
        archs = list(recorded.architectures) if recorded is not None else ["CKF"]
        return Model(system, source, json.dumps(system_to_dict(system)), archs)

    def sensor_dims(self, system: System) -> list[tuple[str, int]]:
        return [(s.name, s.dim) for s in system.sensors]

    def estimator(
        self, system: System, steps: int, runs: int, archs: list[str], sensors: McapFile
    ) -> Estimator:
        topics = [f"/sensors/{s.name}" for s in system.sensors]
        system = with_message_covariances(on_times(system, sensors), sensors)
        return _StateEstimator(system, steps, runs, archs, topics, sensors.times())

    def evaluator(self, sc: Scenario, est: McapFile, prov: Prov, sens: Sens = None) -> Evaluator:
        return _StateEvaluator(sc, est, prov, sens)


class _StateEstimator(Estimator):
    def __init__(
        self,
        system: System,
        steps: int,
        runs: int,
        archs: list[str],
        topics: list[str],
        times: np.ndarray,
    ) -> None:
        self.system, self.K, self.M, self.archs, self.topics = system, steps, runs, archs, topics
        self.times = times
        self.plans: dict[tuple[str, bytes], Plan] = {}
        self.pattern: np.ndarray | None = None  # the measurement pattern shared by every run
        self.per_run = False

    def block_runs(self, requested: int | None) -> int:
        return block_runs(self.K, self.M, requested)

    def estimate(self, run_offset: int, data: dict[str, np.ndarray]) -> dict[str, StepWriter]:
        z = np.concatenate([data[t] for t in self.topics], axis=-1)
        if not self.system.linear:  # EKF/UKF: every run has its own linearisation
            self.per_run = True
            return step_writers(self.system, self.archs, z, self.times, run_offset)
        block_pattern = shared_pattern(z)
        if block_pattern is None or (
            self.pattern is not None and (block_pattern != self.pattern).any()
        ):
            self.per_run = True
        elif self.pattern is None:
            self.pattern = block_pattern
        out: dict[str, StepWriter] = {}
        for a in self.archs:
            if block_pattern is not None:
                key = (a, np.packbits(block_pattern).tobytes())
                if key not in self.plans:
                    mask = None if block_pattern.all() else block_pattern
                    self.plans[key] = build_plan(self.system, a, self.K, mask)
                est = run_plan(self.plans[key], z)
            else:
                est = estimate(self.system, z, a)
            out[a] = _estimate_writer(est.mean, est.cov, est.shared_cov)
        return out

    def provenance(self) -> dict[str, str]:
        # The evaluator's exact analysis needs it: a shared pattern is analysed with the same
        # mask, per-run patterns are not.
        if self.per_run or self.pattern is None:
            return {"measurement_pattern": "per-run"}
        if self.pattern.all():
            return {"measurement_pattern": "complete"}
        return {"measurement_pattern": json.dumps(self.pattern.astype(int).tolist())}


def on_times(system: System, file: McapFile) -> System:
    """The system on the instants of a log (`System.on_times`)."""
    return system.on_times(file.times())


def _estimate_writer(mean: np.ndarray, cov: np.ndarray, shared: bool) -> StepWriter:
    def write(w: McapWriter, topic: str, k: int, t: float, off: int) -> None:
        w.write_estimate(topic, k, t, off, mean[:, k], cov[k] if shared else cov[:, k])

    return write


def _analysable(prov: dict[str, str], filter_sys: System, truth_sys: System):
    """(truth model as the filter saw it, measurement mask, per run) for the exact analysis, or
    None.

    The filter stacks its sensors in its own order, so the truth is re-ordered to match by
    sensor name (a `--model` may list them differently or use only some); sensors the truth
    does not have leave no exact analysis. `per run`: the runs' patterns differ (the mask is
    then None: each block's plans are built from its sensor readings).
    """
    if not (filter_sys.linear and truth_sys.linear):  # no exact analysis: the PCRB instead
        return None
    pattern = prov.get("measurement_pattern", "complete")
    names = [s.name for s in truth_sys.sensors]
    if any(s.name not in names for s in filter_sys.sensors):
        return None
    seen = truth_sys.subset([names.index(s.name) for s in filter_sys.sensors])
    if any(a.dim != b.dim for a, b in zip(seen.sensors, filter_sys.sensors, strict=True)):
        return None
    if pattern == "per-run":
        return seen, None, True
    mask = None if pattern == "complete" else np.array(json.loads(pattern), dtype=bool)
    return seen, mask, False


def _known(arch: str, system: System) -> bool:
    try:
        parse_arch(arch, [s.name for s in system.sensors])
    except ValueError:
        return False
    return True


class _StateEvaluator(Evaluator):
    """MSE, NEES, DM per architecture with exact expected values; sample runs; state plane."""

    def __init__(
        self, sc: Scenario, est: McapFile, prov: dict[str, str], sens: McapFile | None = None
    ) -> None:
        # here, not at the top: core.metrics imports scipy.special (~0.25 s), which only an
        # evaluation needs, and this module is loaded by simulate and estimate too
        from fusionlog.core.metrics import MetricsAccumulator

        self.topics = [t for t in est.topics if t.startswith("/estimates/")]
        if not self.topics:
            have = ", ".join(sorted(est.topics)) or "none"
            raise FusionlogError(f"{est.path}: no /estimates/<ARCH> topics (topics: {have})")
        self.archs = [t.removeprefix("/estimates/") for t in self.topics]
        self.sc, self.prov = sc, prov
        truth_sys = on_times(sc.system, est)
        filter_sys = (
            system_from_dict(json.loads(prov["model"]), f"{est.path}: provenance model")
            if "model" in prov
            else sc.system
        )
        self.filter_sys = on_times(filter_sys, est)
        if sens is not None:  # an imported log's per-message R, for the filter and the truth
            self.filter_sys = with_message_covariances(self.filter_sys, sens)
            truth_sys = with_message_covariances(truth_sys, sens)
        if self.filter_sys.n != truth_sys.n:
            raise FusionlogError(
                f"{est.path}: estimates of {self.filter_sys.n} states, the truth has {truth_sys.n}"
            )
        self.K, self.M = est.steps() - 1, est.runs()
        self.truth_sys = truth_sys
        self.analysable = _analysable(prov, self.filter_sys, truth_sys)
        n = truth_sys.n
        self.accs = {a: MetricsAccumulator(self.K + 1, n) for a in self.archs}
        # Per-run patterns: each run's exact values, summed block by block from its plan (the
        # estimator's, rebuilt from the sensor readings: NaN = absent).
        self.conditional: dict[str, ConditionalExpected] = {}
        if self.analysable is not None and self.analysable[2]:
            self.sensor_topics = [f"/sensors/{s.name}" for s in self.filter_sys.sensors]
            self.conditional = {
                a: ConditionalExpected(self.K + 1, n)
                for a in self.archs
                if _known(a, self.filter_sys)
            }
        # Truth-free consistency (NIS) and each sensor's availability, from the readings.
        from .consistency import NisAccumulator  # core.metrics, as above

        self.has_truth = sens is None or "/truth" in sens.topics
        self.nis: Any = None  # a NisAccumulator
        self.measured: dict[str, np.ndarray] = {}
        self.scheduled: dict[str, np.ndarray] = {}
        self.trace = {a: np.zeros(self.K + 1) for a in self.archs}
        self.measured_points: dict[int, dict[str, np.ndarray]] = {}
        # Only where they say something: a replayed recording (NIS), sensors with their own
        # timing (availability); the paper's scenarios keep their summaries and recordings.
        replay = sc.replay is not None
        timed = replay or any(not s.timing.default for s in sc.system.sensors)
        if (
            timed
            and sens is not None
            and all(f"/sensors/{s.name}" in sens.topics for s in self.filter_sys.sensors)
        ):
            self.sensor_topics = [f"/sensors/{s.name}" for s in self.filter_sys.sensors]
            known = [a for a in self.archs if _known(a, self.filter_sys)]
            if replay:
                self.nis = NisAccumulator(self.filter_sys, known, self.K + 1)
            for s in self.filter_sys.sensors:
                self.scheduled[s.name] = sens.topic_steps(f"/sensors/{s.name}")
                self.measured[s.name] = np.zeros(self.K + 1)
        # Nonlinear models: the posterior Cramer-Rao bound, from the truth and the readings.
        self.pcrb = None if truth_sys.linear else PcrbPart(truth_sys, est.times())
        if self.pcrb is not None:
            self.sensor_topics = self.pcrb.topics
        self.n_samples = min(sc.sample_runs, self.M)
        self.samples: dict[int, tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]] = {}
        self.plane_pts: dict[str, np.ndarray] = {}
        self.plane_truth: np.ndarray | None = None
        self.plane_cov: dict[str, np.ndarray] = {}
        self._series: dict[str, dict[str, np.ndarray]] = {}
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None

    def block_runs(self, requested: int | None) -> int:
        return block_runs(self.K, self.M, requested)

    def add(self, off: int, truth: Array, estimates: Topics, sensors: Readings = None) -> None:
        runs = next(iter(estimates.values()))[0].shape[0]
        x = truth if truth is not None else np.full((runs, self.K + 1, self.sc.system.n), np.nan)
        if x.shape[-1] != self.sc.system.n:
            raise FusionlogError(f"/truth has {x.shape[-1]} values per run, not {self.sc.system.n}")
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
                self._add_conditional(z)
        for a, t in zip(self.archs, self.topics, strict=True):
            mean, cov = estimates[t]
            if mean.shape[-1] != x.shape[-1]:
                raise FusionlogError(
                    f"{t}: estimates of {mean.shape[-1]} states, the truth has {x.shape[-1]}"
                )
            self.trace[a] += np.trace(cov, axis1=-2, axis2=-1).sum(axis=0) * (
                x.shape[0] if cov.ndim == 3 else 1
            )
            if self.has_truth:
                self.accs[a].add(x, mean, cov)
            if self.sc.plane_view and off == 0:
                self.plane_truth = x[0]
                self.plane_pts[a] = np.moveaxis(mean[:PLANE_POINTS], 0, 1)  # (K+1, P, 2)
                self.plane_cov[a] = cov if cov.ndim == 3 else cov[0]
            for r in range(off, min(off + x.shape[0], self.n_samples)):
                c = cov if cov.ndim == 3 else cov[r - off]
                std = np.sqrt(np.clip(np.diagonal(c, axis1=-2, axis2=-1), 0, None))
                self.samples.setdefault(r, (x[r - off], {}))[1][a] = (mean[r - off], std)

    def _add_consistency(self, sensors: dict[str, np.ndarray], estimates: dict[str, Any]) -> None:
        """NIS of each architecture and the sensors' availability, for one block."""
        if self.nis is not None:
            z = np.concatenate([sensors[t] for t in self.sensor_topics], axis=-1)
            self.nis.add(z, {a: estimates[f"/estimates/{a}"] for a in self.nis.archs})
            if not self.measured_points:  # the first run's readings of a state, under its estimates
                H = self.filter_sys.linear_measurement()
                for s, t, sl in zip(
                    self.filter_sys.sensors,
                    self.sensor_topics,
                    self.filter_sys.sensor_slices,
                    strict=True,
                ):
                    for row, h in enumerate(H[sl]):
                        if np.count_nonzero(h) == 1 and h.max() == 1.0:
                            state = int(np.argmax(h))
                            self.measured_points.setdefault(state, {})[s.name] = sensors[t][
                                0, :, row
                            ]
        for s, t in zip(self.filter_sys.sensors, self.sensor_topics, strict=True):
            self.measured[s.name] += (~np.isnan(sensors[t]).any(axis=-1)).sum(axis=0)

    def _add_conditional(self, z: np.ndarray) -> None:
        """Each run's exact statistics given its measurement pattern (z: the block's stacked
        readings, (runs, K+1, m)), added to the run sums; a pattern shared by the block's
        runs is analysed once."""
        seen = self.analysable[0]
        pattern = shared_pattern(z)
        for a, acc in self.conditional.items():
            if pattern is not None:
                mask = None if pattern.all() else pattern
                acc.add(analyse(build_plan(self.filter_sys, a, self.K, mask), seen), z.shape[0])
            else:
                acc.add(analyse(build_plan(self.filter_sys, a, self.K, ~np.isnan(z)), seen))

    def _expected(self, a: str) -> tuple[Expected | ConditionalExpected | None, bool]:
        """The exact expected values of architecture `a` (None: there are none) and whether
        they are conditional on the drawn patterns (the run average of each run's)."""
        if self.analysable is None or not _known(a, self.filter_sys):
            return None, False
        truth_seen, mask, per_run = self.analysable
        if not per_run:
            return analyse(build_plan(self.filter_sys, a, self.K, mask), truth_seen), False
        cond = self.conditional.get(a)
        # every run the Monte Carlo metrics saw must be in the average (a caller that merges
        # accumulators from elsewhere, without their readings, leaves none)
        if cond is None or cond.runs != self.accs[a].runs:
            return None, False
        return cond, True

    def summary(self) -> dict[str, Any]:
        arch_summary = {}
        nis = self.nis.summary(self.sc.confidence) if self.nis is not None else {}
        for a in self.archs:
            if not self.has_truth:  # a recorded log without truth: what needs none
                mean_trace = float(np.nanmean(self.trace[a] / self.M))
                arch_summary[a] = {"mean_trace": mean_trace} | ({"nis": nis[a]} if a in nis else {})
                continue
            res = self.accs[a].finalize(self.sc.confidence)
            ex, conditional = self._expected(a)
            kw = (
                {"expected_mse": ex.mse_per_state, "expected_nees": ex.nees, "expected_dm": ex.dm}
                if ex is not None
                else {}
            )
            self._series[a] = res.series(**kw)
            arch_summary[a] = res.summary(**kw)
            if self.pcrb is not None:  # no exact analysis: `expected` is null, the PCRB stands
                arch_summary[a]["expected"] = None
            if conditional:  # DESIGN.md "summary.json": conditional on the drawn patterns
                arch_summary[a]["expected"]["conditional"] = True
            if a in nis:
                arch_summary[a]["nis"] = nis[a]
            if self._bounds is None:
                self._bounds = (res.nees_lower, res.nees_upper)
        self._summary = {
            "scenario": self.sc.name,
            "seed": self.sc.seed,
            "runs": self.M,
            "steps": self.K,
            "state_names": list(self.sc.state_names),
            "confidence": self.sc.confidence,
            "architectures": arch_summary,
        }
        if self.pcrb is not None:  # DESIGN.md: no exact analysis, the PCRB beside the values
            self._summary["pcrb"] = self.pcrb.summary()
        return self._summary

    def _plane(self) -> dict[str, Any] | None:
        if not self.sc.plane_view or self.plane_truth is None:
            return None
        from fusionlog.core.metrics import chi2_quantile  # loaded by __init__ (see there)

        inputs = {
            f"input {s.name}": build_plan(self.filter_sys, f"SKF:{s.name}", self.K).reported_cov
            for s in self.filter_sys.sensors
        }
        return {
            "truth": self.plane_truth,
            "estimates": self.plane_pts,
            "ellipses": {**inputs, **self.plane_cov},
            # the ellipse of a 2-D Gaussian at the confidence: chi-square with 2 dof
            "scale": float(np.sqrt(chi2_quantile(self.sc.confidence, 2))),
        }

    def write_recording(self, file: BinaryIO, times: np.ndarray, provenance: dict) -> None:
        from fusionlog.io.rrd import write_recording  # rerun: slow to import, needed only here

        from .consistency import availability

        write_recording(
            file,
            scenario_name=self.sc.name,
            seed=self.sc.seed,
            times=times,
            state_names=self.sc.state_names,
            series=self._series,
            summary=self._summary,
            nees_bounds=self._bounds,
            confidence=self.sc.confidence,
            sample_runs=self.samples,
            properties={"scenario": self.sc.source, "provenance": provenance},
            plane=self._plane(),
            availability={
                name: availability(self.measured[name], self.scheduled[name], self.M)
                for name in self.measured
            },
            nis=self.nis.series(self.sc.confidence) if self.nis is not None else None,
            traces=None if self.has_truth else {a: t / self.M for a, t in self.trace.items()},
            measured=self.measured_points,
            pcrb=None if self.pcrb is None else self.pcrb.per_state(),
        )
