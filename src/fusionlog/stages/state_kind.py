"""The state kind's stage hooks: linear Gaussian systems and the paper's fusion architectures.

The hooks are adapters: simulation is :func:`fusionlog.core.simulate.simulate`, estimation of a
block read from MCAP is :func:`fusionlog.driver.estimate_block` (with one
`PlanCache` per command: a plan per architecture and measurement pattern), and evaluation is
:class:`.evaluator.StateEvaluator`, which accumulates arrays and returns an `Evaluation` that
:func:`fusionlog.io.rrd.write_evaluation` writes.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from fusionlog.core.architectures.long_log import steady_log
from fusionlog.core.late_policy import is_late, random_delays
from fusionlog.core.model import System
from fusionlog.core.names import check_architectures
from fusionlog.core.reference import reference_paths
from fusionlog.core.simulate import simulate
from fusionlog.driver import KeptPlans, PlanCache, estimate_block
from fusionlog.errors import FusionlogError, NumericalError
from fusionlog.io.mcap import ESTIMATE, TRUTH, McapFile, McapWriter, arch_of, sensor_topic
from fusionlog.io.mcap.layout import StepMask
from fusionlog.io.mcap.run_steps import RunColumn
from fusionlog.io.mcap.topics import ESTIMATES_PREFIX
from fusionlog.scenario import Scenario, load_model, system_from_dict, system_to_dict
from fusionlog.scenario.model_section import bytes_per_instant

from .common import block_runs
from .evaluator import SensorLog, StateEvaluator
from .hooks import Estimator, Kind, Model, Prov, Sens, StepWriter
from .noise import message_covariances, with_message_covariances


def check_discretisable(system: System, truth: Scenario, model: str, where: str) -> None:
    """A filter model for the instants of `truth`, a simulated scenario: explicit F, Q hold for
    dt only, so irregular instants need a model discretisable for any interval (the rule a
    scenario's own model meets on load, DESIGN.md "Timing"); else FusionlogError."""
    if truth.replay is None and not truth.schedule.regular and system.continuous is None:
        if system.motion_model is None:
            raise FusionlogError(
                f"{model}: model.F: explicit F, Q hold for dt only, but the instants of {where} "
                "are irregular: give kind = 'constant-velocity' (n0, axes) or kind = "
                "'continuous' (A, Qc)"
            )


def with_filter(system: Any, name: str | None, where: str = "--filter") -> Any:
    """The system with its local filter set by ``--filter`` (None: as recorded); errors name
    the option as `where` (the Python API's argument: "filter")."""
    if name is None:
        return system
    from fusionlog.scenario.nonlinear_syntax import FILTERS

    if not isinstance(system, System):
        raise FusionlogError(f"{where}: only state scenarios have a local filter")
    if not isinstance(name, str) or name not in FILTERS:
        what = repr(name) if isinstance(name, str) else f"{name!r} ({type(name).__name__})"
        raise FusionlogError(f"{where}: unknown filter {what} (known: {', '.join(FILTERS)})")
    return dataclasses.replace(system, filter=name)


def with_late(system: Any, late: str | None, where: str = "--late") -> Any:
    """The system with its policy for late measurements set by ``--late`` (None: as
    recorded), refused in one line where its late sensors cannot take it."""
    if late is None:
        return system
    from fusionlog.core.late_policy import LATE_POLICIES, system_refusal

    if not isinstance(system, System):
        raise FusionlogError(f"{where}: only state scenarios have late measurements")
    if late not in LATE_POLICIES:
        raise FusionlogError(
            f"{where}: unknown policy {late!r} (known: {', '.join(LATE_POLICIES)})"
        )
    system = dataclasses.replace(system, late=late)
    why = system_refusal(system)
    if why is not None:
        raise FusionlogError(f"{where}: {why[1]}")
    return system


def scenario_with_late(sc: Scenario, late: str | None, archs: Sequence[str] = ()) -> Scenario:
    """The scenario with ``--late`` applied to its system (`with_late`), the architectures
    that will run (`archs`, else the scenario's) checked against it."""
    if late is None:
        return sc
    system = with_late(sc.system, late)
    check_architectures(list(archs) or sc.architectures, system, f"--late {late}")
    return dataclasses.replace(sc, system=system)


def step_writers(
    plans: PlanCache, archs: list[str], z: np.ndarray, run_offset: int
) -> dict[str, Any]:
    """The estimate stage's writers of a block (`plans`: the system and instants): each
    architecture's filter advances one instant when its message for that instant is written
    (the estimator's writers are called for k = 0..K in order), so only one instant of per-run
    covariances is held, not all of them (`core.nonlinear.estimate_steps`)."""
    from fusionlog.core.nonlinear import estimate_steps

    system, times = plans.system, plans.times  # the system is on the log's instants

    def writer(arch: str) -> Any:
        arrival = plans.block_arrivals(run_offset, z.shape[0])
        steps = estimate_steps(system, arch, z, times, run_offset, arrival)

        def write(w: Any, topic: str, k: int, t: float, off: int) -> None:
            mean, cov = next(steps)
            w.write_estimate(topic, k, t, off, mean, cov)

        return write

    return {a: writer(a) for a in archs}


class StateKind(Kind):
    name = "state"

    def system_fields(self, scenario: Scenario) -> dict[str, str]:
        return {"system": json.dumps(system_to_dict(scenario.system))}

    def bytes_per_run_step(self, scenario: Scenario) -> int:
        return bytes_per_instant(scenario.system, len(scenario.architectures))

    def sensor_names(self, system: System) -> list[str]:
        return [s.name for s in system.sensors]

    def check_architectures(self, names: Sequence[str], system: System, where: str) -> list[str]:
        return check_architectures(names, system, where)

    def simulate(
        self, scenario: Scenario, run_offset: int, runs: int
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        sched = scenario.schedule
        system = scenario.system.on_times(sched.times)
        measures = None if sched.measures.all() else sched.measures
        try:
            x, z = simulate(system, sched.steps, scenario.seed, run_offset, runs, measures)
        except NumericalError as e:  # the core names the step; the scenario's file here
            raise NumericalError(f"{scenario.path or scenario.name}: {e}") from None
        return x, [z[..., sl] for sl in system.sensor_slices]

    def simulate_blocks(self, scenario: Scenario, block: int) -> Any:
        """One run (linear or not, regular instants or not, with dropouts or not) longer than a
        block of time: `core.simulate.one_run_blocks` (the numbers of `simulate`)."""
        from fusionlog.core.simulate import one_run_blocks

        sched, system = scenario.schedule, scenario.system
        if scenario.runs != 1 or sched.steps + 1 <= block:
            return None
        system = system.on_times(sched.times)
        measures = None if sched.measures.all() else sched.measures
        blocks = one_run_blocks(system, sched.steps, scenario.seed, block, measures)
        return ((k0, k1, x, [z[..., sl] for sl in system.sensor_slices]) for k0, k1, x, z in blocks)

    def arrivals(self, scenario: Scenario, run_offset: int, runs: int) -> np.ndarray | None:
        from fusionlog.core.late_policy import draw_arrivals

        return draw_arrivals(scenario.system, scenario.times, scenario.seed, run_offset, runs)

    def arrival_blocks(self, scenario: Scenario, block: int) -> Any:
        """`core.late_policy.arrival_blocks`, NaN for the sensors on time (no arrival field,
        as `simulate_to` writes the whole run's)."""
        from fusionlog.core.late_policy import arrival_blocks

        system = scenario.system
        got = arrival_blocks(system, scenario.times, scenario.seed, block)
        if got is None:
            return None
        on_time = [not s.timing.late for s in system.sensors]
        return (np.where(on_time, np.nan, a) for a in got)

    def latencies(self, scenario: Scenario) -> np.ndarray | None:
        system = scenario.system
        if not is_late(system) or random_delays(system):
            return None
        return np.array([s.timing.latency[0] for s in system.sensors])

    def model(self, sensors: McapFile, recorded: Scenario | None, model_path: Path | None) -> Model:
        if model_path is None:
            recorded = self.recorded(sensors, recorded)
            system, source = recorded.system, "scenario"
        else:
            dt = recorded.dt if recorded is not None else None
            system, source = load_model(model_path, "state", dt), str(model_path)
            if recorded is not None and system.n != recorded.system.n:
                raise FusionlogError(
                    f"{model_path}: the model has {system.n} states, "
                    f"the scenario recorded in {sensors.path} has {recorded.system.n}"
                )
            if recorded is not None:
                check_discretisable(system, recorded, str(model_path), str(sensors.path))
        archs = list(recorded.architectures) if recorded is not None else ["CKF"]
        return Model(system, source, json.dumps(system_to_dict(system)), archs)

    def sensor_dims(self, system: System) -> list[tuple[str, int]]:
        return [(s.name, s.dim) for s in system.sensors]

    def estimator(
        self,
        system: System,
        steps: int,
        runs: int,
        archs: list[str],
        sensors: McapFile,
        kept: KeptPlans | None = None,
    ) -> Estimator:
        topics = [sensor_topic(s.name) for s in system.sensors]
        long = _long_one_run(steps, runs)  # its per-message R read block by block
        system = with_message_covariances(system.on_times(sensors.times()), sensors, long)
        plans = PlanCache(system, steps, times=sensors.times(), one_run=runs == 1, kept=kept)
        est = _StateEstimator(plans, runs, archs, topics)
        # a long one-run log's arrivals are read block by block (`.late_blocks`); the whole
        # run's path reads them all on its first block
        est.load = lambda: recorded_arrivals(plans, sensors, topics, runs)
        if not long:
            est.arrivals()
        return est

    def evaluator(
        self,
        sc: Scenario,
        est: McapFile,
        prov: Prov,
        sens: Sens = None,
        kept: KeptPlans | None = None,
    ) -> StateEvaluator:
        """The evaluator of an estimates file: its architectures, the filters' model (recorded
        in its provenance, else the scenario's) and the truth's, on its instants, with the
        sensors log's per-message R where it has them."""
        archs = [arch_of(t) for t in est.topics if t.startswith(ESTIMATES_PREFIX)]
        if not archs:
            have = ", ".join(sorted(est.topics)) or "none"
            raise FusionlogError(f"{est.path}: no /estimates/<ARCH> topics (topics: {have})")
        times = est.times()
        truth_sys = sc.system.on_times(times)
        filter_sys = (
            system_from_dict(json.loads(prov["model"]), f"{est.path}: provenance model")
            if "model" in prov
            else sc.system
        ).on_times(times)
        log = None
        if sens is not None:  # an imported log's per-message R, for the filter and the truth
            names = [s.name for s in (*filter_sys.sensors, *truth_sys.sensors)]
            long = _long_one_run(len(times) - 1, est.runs())  # read block by block
            covs = message_covariances(names, sens, long)
            filter_sys = with_message_covariances(filter_sys, sens, covs=covs)
            truth_sys = with_message_covariances(truth_sys, sens, covs=covs)
            log = _sensor_log(sc, filter_sys, sens)
        return StateEvaluator(
            sc, archs, filter_sys, truth_sys, est.runs(), times, prov, log, str(est.path), kept
        )

    def write_evaluation(self, file: BinaryIO, evaluation: Any) -> None:
        from fusionlog.io.rrd import write_evaluation  # rerun: slow to import, needed only here

        write_evaluation(file, evaluation)


def recorded_arrivals(
    plans: PlanCache, sensors: McapFile, topics: list[str], runs: int
) -> np.ndarray | None:
    """When each reading of the log arrived, (runs, K+1, S) s (its messages' arrival field;
    on time where a topic has none), where the cache's delays differ per run; else None."""
    if not random_delays(plans.system):  # fixed latencies: the model says when
        return None
    from fusionlog.io.mcap.arrival import read_arrivals

    got = read_arrivals(sensors.path, topics, runs, plans.steps + 1, on_time=sensors.times())
    return np.stack(list(got.values()), -1)


def _long_one_run(steps: int, runs: int) -> bool:
    """Whether a log may be taken in blocks of time (`driver.long_log`): one run longer than a
    block, not on the reference paths."""
    from fusionlog.driver.long_log import time_block

    return runs == 1 and steps + 1 > time_block() and not reference_paths()


def _sensor_log(sc: Scenario, filter_sys: System, sens: McapFile) -> SensorLog:
    """Whether the sensors log has the truth, and each sensor's scheduled instants where
    availability says something: a replayed recording, or sensors with their own timing."""
    timed = sc.replay is not None or any(not s.timing.default for s in sc.system.sensors)
    topics = [sensor_topic(s.name) for s in filter_sys.sensors]
    scheduled = None
    if timed and all(t in sens.topics for t in topics):
        scheduled = {  # bits: a long log's blocks unpack their own (issue 34)
            s.name: StepMask.of_mask(sens.topic_steps(t))
            for s, t in zip(filter_sys.sensors, topics, strict=True)
        }
    truth = sens.metadata.get("fusionlog.scenario", {}).get("replay_truth")
    late = PlanCache(filter_sys, sens.steps() - 1, clock=sens.times())

    def load() -> np.ndarray | None:
        return recorded_arrivals(late, sens, topics, sens.runs())

    # a long one-run log's arrivals: read block by block in blocks of time, else on first use
    long = _long_one_run(late.steps, sens.runs())
    return SensorLog(
        TRUTH in sens.topics, scheduled, json.loads(truth) if truth else None,
        None if long else load(), sens if long else None, load if long else None,
    )  # fmt: skip


class _StateEstimator(Estimator):
    """Blocks read from a sensors file through `estimate_block`, one plan cache for all."""

    def __init__(self, plans: PlanCache, runs: int, archs: list[str], topics: list[str]) -> None:
        self.plans, self.M, self.archs, self.topics = plans, runs, archs, topics
        self.load: Any = None  # reads the log's arrivals (`recorded_arrivals`), once

    def arrivals(self) -> None:
        """The log's arrivals into the plan cache, read on first use."""
        if self.load is not None:
            self.plans.arrivals, self.load = self.load(), None

    def block_runs(self, requested: int | None) -> int:
        return block_runs(self.plans.steps, self.M, requested)

    def estimate(self, run_offset: int, data: dict[str, np.ndarray]) -> dict[str, StepWriter]:
        self.arrivals()
        z = np.concatenate([data[t] for t in self.topics], axis=-1)
        if not self.plans.system.linear:  # EKF/UKF: each instant computed as it is written
            self.plans.patterns.append(None)  # per-run covariances (provenance)
            return step_writers(self.plans, self.archs, z, run_offset)
        block = estimate_block(
            self.plans.system, self.archs, z, cache=self.plans, run_offset=run_offset
        )
        return {
            a: _estimate_writer(e.mean, e.cov, e.shared_cov) for a, e in block.estimates.items()
        }

    def time_windows(self, sensors: McapFile) -> Any:
        """A long one-run log in blocks of time (`driver.long_log`): a steady model with every
        reading present through its short plans, a recorded replay or a simulated run without
        steady plans (irregular instants, per-message R, readings missing or lost at dropouts)
        through the plan-free path carried block to block, a nonlinear model through its
        EKF/UKF filters (and their late policies) carried block to block; None otherwise (a
        log short enough for one block, linear late readings without late plans standing for
        the log, the reference paths, a model `ReplayBlocks.of` refuses: the whole run)."""
        from fusionlog.core.architectures.replay_blocks import ReplayBlocks
        from fusionlog.driver.long_log import (
            long_estimates,
            replay_long_estimates,
            spool_readings,
            time_block,
        )

        plans, B = self.plans, time_block()
        system = plans.system
        if not _long_one_run(plans.steps, self.M):  # the same rule that defers its arrivals
            return None
        if is_late(system) and system.linear:  # late plans carried (issue 30), else whole
            return self._late_windows(sensors, B)
        if not system.linear:  # EKF/UKF (late or not): their states carried block to block
            return self._nonlinear_windows(sensors, B)
        steady = system.Rs is None and system.time_invariant
        log = steady_log(system, self.archs, plans.steps, plans.criterion) if steady else None
        blocks = None if log is not None else ReplayBlocks.of(system, self.archs, plans.steps, B)
        if log is None and blocks is None:
            return None
        spool = spool_readings(sensors.iter_time_blocks(self.topics, B), self.topics, system.m)
        if spool.missing and blocks is None:  # the short plans stand for a complete log
            blocks = ReplayBlocks.of(system, self.archs, plans.steps, B)
            if blocks is None:
                spool.close()
                return None
        if blocks is None:
            plans.patterns.append(np.packbits(np.ones((plans.steps + 1, system.m), bool)).tobytes())
            out = long_estimates(log, spool, B)
        else:
            plans.patterns.append(np.packbits(spool.present(B)).tobytes())
            out = replay_long_estimates(blocks, spool, B)
        return (
            (k0, k1, {a: _estimate_writer(e.mean, e.cov, True, k0) for a, e in got.items()})
            for k0, k1, got in out
        )

    def _late_windows(self, sensors: McapFile, B: int) -> Any:
        """A long one-run log with late sensors in blocks of time: at fixed latencies with
        every reading present the late plans of a short horizon, their state (the latency
        window) carried across the blocks (`core.latency_long`); with delays drawn or
        recorded, or readings missing, or a covariance per message, the plan-free stacked
        filters carried (`core.latency_blocks`, `.late_blocks`: CKF, HKF, SKF and the
        per-sensor rules, under reprocess and neglect), or, retrodicted (also where no short
        plans stand for the log), each block's plans with the state of the block before
        (`core.retrodict_blocks`: every architecture but FBS); None otherwise (FBS, the CKF
        of correlated readings arriving apart with each message's R: the whole run)."""
        from fusionlog.core.latency_blocks import LateBlocks
        from fusionlog.core.latency_long import late_steady_log
        from fusionlog.core.retrodict_blocks import RetroBlocks
        from fusionlog.driver.long_log import long_estimates, spool_readings

        from .late_blocks import late_estimates

        plans = self.plans
        system = plans.system
        log = late_steady_log(system, self.archs, plans.steps, plans.criterion, sensors.times())
        kind = RetroBlocks if system.late == "retrodict" else LateBlocks
        if log is None and not kind.covers(system, self.archs):
            return None  # the plans of the whole run
        spool = spool_readings(sensors.iter_time_blocks(self.topics, B), self.topics, system.m)
        if log is not None and not spool.missing:
            plans.patterns.append(np.packbits(np.ones((plans.steps + 1, system.m), bool)).tobytes())
            out = long_estimates(log, spool, B)
        else:
            blocks = kind.of(
                system, self.archs, plans.steps, sensors.times(), B, plans.criterion, spool.missing
            )
            if blocks is None:  # the plans of the whole run
                spool.close()
                return None
            # the estimates' measurement pattern as the whole run's path records it
            per_run = random_delays(system)
            plans.patterns.append(None if per_run else np.packbits(spool.present(B)).tobytes())
            out = late_estimates(blocks, sensors, system, self.topics, spool, B)
        return (
            (k0, k1, {a: _estimate_writer(e.mean, e.cov, True, k0) for a, e in got.items()})
            for k0, k1, got in out
        )

    def _nonlinear_windows(self, sensors: McapFile, B: int) -> Any:
        """A long nonlinear one-run log in blocks of time (`core.nonlinear.long_log`), its
        readings spooled (FBS reads them back in reverse; the late policies read the last W
        instants again); late readings arrive when the log says (drawn or recorded delays:
        its arrival fields read block by block, `.late_blocks.arrival_blocks`, and spooled:
        each architecture's policy reads them twice) or with the sensors' fixed latencies."""
        from fusionlog.core.nonlinear.long_log import estimate_blocks
        from fusionlog.driver.long_log import Spool, spool_readings

        from .late_blocks import arrival_blocks

        plans, topics, system = self.plans, self.topics, self.plans.system
        blocks = sensors.iter_time_blocks(topics, B)
        spools = [spool_readings(blocks, topics, system.m)]
        plans.patterns.append(None)  # per-run covariances (provenance), as the whole run's
        arrival = None
        if random_delays(system):  # (fixed latencies: the model says when)
            spools.append(Spool(len(topics)))
            try:
                k0 = 0
                for a in arrival_blocks(sensors, system, topics, B):
                    spools[1].write(k0, a)
                    k0 += len(a)
            except BaseException:
                for s in spools:
                    s.close()
                raise
            arrival = lambda a, b: spools[1].read(a, b)[None]  # noqa: E731

        def windows() -> Any:
            try:
                read = lambda a, b: spools[0].read(a, b)[None]  # noqa: E731
                got = estimate_blocks(system, self.archs, read, plans.times, B, arrival)
                for k0, k1, out in got:
                    yield k0, k1, {a: _estimate_writer(*e, False, k0) for a, e in out.items()}
            finally:
                for s in spools:
                    s.close()

        return windows()

    def provenance(self) -> dict[str, str]:
        # The evaluator's exact analysis needs it: a shared pattern is analysed with the same
        # mask, per-run patterns are not.
        return self.plans.provenance()


class _estimate_writer:  # noqa: N801 - a StepWriter, called as the function it replaced
    """Writes step k of a block of runs (mean (runs, w, n)) whose first instant is k0; a
    one-run block's steps also as one column at once (`column`)."""

    __slots__ = ("mean", "cov", "shared", "k0")

    def __init__(self, mean: np.ndarray, cov: np.ndarray, shared: bool, k0: int = 0) -> None:
        self.mean, self.cov, self.shared, self.k0 = mean, cov, shared, k0

    def __call__(self, w: McapWriter, topic: str, k: int, t: float, off: int) -> None:
        k -= self.k0
        cov = self.cov[k] if self.shared else self.cov[:, k]
        w.write_estimate(topic, k + self.k0, t, off, self.mean[:, k], cov)

    def column(self, topic: str) -> RunColumn | None:
        """The messages of every step of a one-run block (`McapWriter.write_run_steps`)."""
        if self.mean.shape[0] != 1:
            return None
        return RunColumn(topic, ESTIMATE, self.mean[0], self.cov if self.shared else self.cov[0])
