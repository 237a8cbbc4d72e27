"""The Python API: the pipeline on numpy arrays, nothing written to disk unless asked.

    import fusionlog as fl
    sc = fl.load("pipeline/ajgl2009.toml")       # a validated scenario
    sim = fl.simulate(sc, runs=1000, seed=3)      # .times (K+1,), .truth (M, K+1, n),
                                                  # .measurements {sensor: (M, K+1, m)}, NaN = none
    est = fl.estimate(sc, sim, ["CKF", "MSC"])    # {arch: .mean (M, K+1, n),
                                                  #        .cov (M, K+1, n, n)}
    ev = fl.evaluate(sc, sim, est)                # .summary, .table(), .save("evaluation.rrd")

The CLI is an adapter over the same functions: `simulate` is the simulate stage's hook (the
random streams belong to chunks of runs, so the runs are those `fusionlog simulate` writes),
`estimate` is `driver.estimate_block` in the estimate stage's blocks of runs with
one plan cache, and `evaluate` is the state evaluator fed the same blocks: the same scenario,
runs and seed give the CLI's numbers.

Bad arguments fail as the CLI does: one `FusionlogError` (a `ValidationError` for the shapes
and values of arrays) naming the argument (`runs`, `filter`, `architectures`,
`sim.measurements['s1']`, `estimates['CKF'].cov`) and the problem (`fusionlog.arguments`),
never numpy's error from deep inside; `simulate`
refuses runs that cannot all be held in memory before allocating them
(`scenario.scenario_base.memory_shortfall`, the CLI's memory decision).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _API
from .arguments import (
    check_architecture_names,
    check_estimate_shapes,
    check_estimate_values,
    check_simulation,
)
from .core import evaluation
from .core.architectures import Estimate as BlockEstimate
from .core.model import System
from .core.names import check_architectures
from .driver import PlanCache, estimate_block
from .errors import FusionlogError, ValidationError
from .io.mcap import estimates_topic, sensor_topic
from .scenario import Scenario, load_scenario, scenario_with
from .scenario.scenario_base import memory_shortfall
from .stages.common import block_runs
from .stages.evaluator import SensorLog, StateEvaluator
from .stages.kinds import kind_of
from .stages.noise import with_covariances
from .stages.state_kind import check_discretisable

__all__ = list(_API)  # the names `fusionlog` itself offers


@dataclass
class Simulation:
    """Runs of a scenario: simulated, or a replay's recorded readings (one run).

    `times` (K+1,) seconds; `truth` (M, K+1, n), NaN where a replay's truth has no reading
    (None: a replay without truth); `measurements[sensor]` (M, K+1, m) in the sensor's units,
    NaN where it did not measure (its timing) or lost the reading (dropout); `scheduled
    [sensor]` (K+1,) bool, the instants it measures at; `covariances[sensor]` (K+1, m, m) the
    R a recorded sensor's messages carry (NaN at instants without one); `scenario` the
    scenario with the runs, steps and seed used; `z` (M, K+1, m) the measurements stacked as
    in eq. (30). A replay's `times` count seconds from its first instant. `estimate` and
    `evaluate` check these arrays against each other and the scenario (`check`).
    """

    scenario: Scenario
    times: np.ndarray
    truth: np.ndarray | None
    measurements: dict[str, np.ndarray]
    scheduled: dict[str, np.ndarray] = field(default_factory=dict)
    covariances: dict[str, np.ndarray] = field(default_factory=dict)
    #: a replay's truth: {"states", "matched", "unmatched"} (summary.json `truth`), else None
    truth_info: dict | None = None
    #: late sensors: when each reading arrived, {sensor: (M, K+1)} seconds (the MCAP field
    #: `arrival`; DESIGN.md "Late measurements"); sensors on time are not in it
    arrival: dict[str, np.ndarray] = field(default_factory=dict)

    def arrivals(self, system: System) -> np.ndarray | None:
        """When each reading of `system`'s sensors arrived, (M, K+1, S) s (on time where the
        simulation has none), or None when none is late."""
        if not self.arrival:
            return None
        on_time = np.broadcast_to(self.times, (self.runs, len(self.times)))
        return np.stack([self.arrival.get(s.name, on_time) for s in system.sensors], -1)

    @property
    def z(self) -> np.ndarray:
        """The stacked measurements of eq. (30), (M, K+1, m): the simulated scenario's sensors
        side by side in its order (a new array at each access; `stacked` for another model's
        sensors)."""
        return self.stacked(self.scenario.system)

    def stacked(self, system: System) -> np.ndarray:
        """The stacked measurements of eq. (30) of `system`'s sensors (taken by name, in its
        order), (M, K+1, m): what a filter on `system` reads."""
        missing = [s.name for s in system.sensors if s.name not in self.measurements]
        if missing:
            have = ", ".join(self.measurements)
            raise ValidationError(
                f"sim.measurements: no readings of sensor {missing[0]!r}, which the filters' "
                f"model has (the simulation has: {have})"
            )
        return np.concatenate([self.measurements[s.name] for s in system.sensors], axis=-1)

    @property
    def runs(self) -> int:
        """M."""
        return next(iter(self.measurements.values())).shape[0]

    def check(self) -> None:
        """Its arrays agree with each other and with its scenario (`arguments.check_simulation`):
        a ValidationError naming the attribute otherwise (`sim.times`, `sim.measurements['s1']`)."""
        if not isinstance(self.scenario, Scenario):
            raise ValidationError(
                f"sim.scenario: expected a scenario, got {type(self.scenario).__name__}"
            )
        check_simulation(
            self.times,
            self.truth,
            self.measurements,
            self.scheduled,
            self.covariances,
            self.scenario.system,
        )

    def on_instants(self, system: System) -> System:
        """`system` on these instants, with the per-instant R of the recorded covariances
        (what filters run with on these data: `stages.noise.with_covariances`)."""
        system = system.on_times(self.times)
        return with_covariances(system, self.covariances, len(self.times), self.scenario.name)


class Estimate:
    """One architecture's estimates of M runs at instants k = 0..K: `mean` (M, K+1, n) and
    `cov` (M, K+1, n, n), for linear and nonlinear scenarios alike.

    Where every run has the same covariance (a linear model without per-run dropouts: the
    gains are computed once for all runs: docs/internals.md) `cov` is a
    read-only view of one (K+1, n, n) array broadcast over the runs, so it costs no memory
    per run: `shared_cov` is then True and `cov[0]` is that array. Otherwise `cov` holds each
    run's own. NaN in both mean and cov marks an instant without an estimate (no prior yet).
    `Estimate(mean, cov)` takes `cov` (M, K+1, n, n), or (K+1, n, n) shared by every run.
    """

    __slots__ = ("_cov", "_shared", "mean")

    def __init__(self, mean: np.ndarray, cov: np.ndarray) -> None:
        self.mean = mean
        shared = (
            isinstance(mean, np.ndarray)
            and isinstance(cov, np.ndarray)
            and mean.ndim == 3
            and cov.ndim == 3
        )
        self._shared = cov if shared else None
        self._cov = np.broadcast_to(cov, mean.shape[:1] + cov.shape) if shared else cov

    @property
    def cov(self) -> np.ndarray:
        """(M, K+1, n, n): each run's covariance at each instant (see the class)."""
        return self._cov

    @property
    def shared_cov(self) -> bool:
        """Whether every run has the same covariance (`cov` a broadcast view of `cov[0]`)."""
        return self._shared is not None

    def __repr__(self) -> str:
        shared = ", shared by the runs" if self.shared_cov else ""
        shapes = f"mean {np.shape(self.mean)}, cov {np.shape(self.cov)}"
        return f"Estimate({shapes}{shared})"


class Estimates(dict[str, Estimate]):
    """{architecture: Estimate} (`Estimate`: `.mean` (M, K+1, n), `.cov` (M, K+1, n, n)).
    `provenance` is what the estimates file records of the measurement pattern (which exact
    analysis applies)."""

    provenance: dict[str, str]


class Evaluation(evaluation.Evaluation):
    """An evaluation (`core.evaluation.Evaluation`: `.summary` the summary.json dict, per-step
    `.series` per architecture, `.samples`, ...) with the adapters a notebook wants."""

    def table(self) -> str:
        """The results table `fusionlog summary` prints (`report.format_table`)."""
        from .report import format_table

        return format_table(self.summary, self.sensors)

    def save(self, path: str | os.PathLike[str], *, force: bool = False) -> Path:
        """Write the Rerun recording to `path` (atomically, `io.atomic.Outputs`; an existing
        file only with `force`): `io.rrd.write_evaluation`. Returns the path."""
        from .io.atomic import Outputs
        from .io.rrd import write_evaluation  # rerun: slow to import, needed only here

        target = Path(path)
        with Outputs([target], force=force) as outs:
            write_evaluation(outs.open(target), self)
            outs.commit()
        return target


def load(path: str | os.PathLike[str]) -> Scenario:
    """The validated scenario of a TOML file (docs/reference/scenario.md); FusionlogError with
    the file, key and reason when it is not valid."""
    return load_scenario(path)


def simulate(
    scenario: Scenario | str | os.PathLike[str],
    runs: int | None = None,
    seed: int | None = None,
    steps: int | None = None,
) -> Simulation:
    """Simulate `runs` runs (default the scenario's) of K = `steps` steps with `seed`: the
    runs `fusionlog simulate --runs --steps --seed` writes to its sensors file. `scenario` is
    a loaded scenario or the path of its file (`load`); a replay file gives its recorded
    readings as one run (and takes no runs, seed or steps)."""
    scenario = _state_scenario(scenario)
    if scenario.replay is not None:  # refused, not ignored (as `fusionlog run` refuses them)
        given = [
            f"{k}=" for k, v in (("runs", runs), ("seed", seed), ("steps", steps)) if v is not None
        ]
        if given:
            raise FusionlogError(
                f"{scenario.path or scenario.name}: a replay file is one recorded run on its "
                f"measurement times: it takes no {', '.join(given)}"
            )
        return _recorded(scenario)
    sc = scenario_with(scenario, runs=runs, steps=steps, seed=seed, flag="")
    kind = kind_of(sc.kind)
    # all runs are held at once here (`fusionlog simulate` writes blocks of them): refused
    # by the count before anything is allocated, not by a MemoryError gigabytes later
    why = memory_shortfall(sc.instants, kind.bytes_per_run_step(sc), sc.runs)
    if why is not None:
        raise ValidationError(
            f"{sc.path or sc.name}: runs: {sc.runs} runs of {sc.instants} instants (with their "
            f"estimates) need {why}: use fewer runs or steps, or the CLI (`fusionlog run` "
            "holds one block of runs at a time)"
        )
    x, zs = kind.simulate(sc, 0, sc.runs)
    names = [s.name for s in sc.system.sensors]
    measures = sc.schedule.measures  # (K+1, S)
    scheduled = {name: measures[:, j] for j, name in enumerate(names)}
    arr = kind.arrivals(sc, 0, sc.runs)
    arrival = {} if arr is None else {
        s.name: arr[..., j] for j, s in enumerate(sc.system.sensors) if s.timing.late
    }  # fmt: skip
    sim = Simulation(sc, sc.times, x, dict(zip(names, zs, strict=True)), scheduled)
    sim.arrival = arrival
    return sim


def _state_scenario(scenario: Scenario | str | os.PathLike[str]) -> Scenario:
    """A loaded scenario, or the one of a file (`load`), of the state kind."""
    if isinstance(scenario, str | os.PathLike):
        scenario = load(scenario)
    if not isinstance(scenario, Scenario):
        raise ValidationError(
            f"scenario: expected a scenario (fusionlog.load) or its path, got "
            f"{type(scenario).__name__}"
        )
    if scenario.kind != "state":
        raise FusionlogError(
            f"{scenario.path or scenario.name}: the Python API runs state scenarios "
            f"(not {scenario.kind})"
        )
    return scenario


def _recorded(scenario: Scenario) -> Simulation:
    """A replay's readings on their instants (what `fusionlog import` writes), as one run."""
    from .stages.import_data import read_replay  # the decoders: only replays need them

    data = read_replay(scenario)
    sc = data.scenario
    K1, n = len(data.instants), sc.system.n
    measurements, scheduled, covariances = {}, {}, {}
    for sen, r in zip(sc.system.sensors, data.sensors, strict=True):
        z = np.full((1, K1, sen.dim), np.nan)
        z[0, r.at] = r.values
        measurements[sen.name] = z
        scheduled[sen.name] = np.zeros(K1, dtype=bool)
        scheduled[sen.name][r.at] = True
        if r.cov is not None:
            covariances[sen.name] = np.full((K1, sen.dim, sen.dim), np.nan)
            covariances[sen.name][r.at] = r.cov
    truth = None
    if data.truth:
        truth = np.full((1, K1, n), np.nan)
        truth[0, data.truth["at"]] = data.truth["values"]
    times = (data.instants - data.instants[0]) / 1e9
    info = data.truth_info or None
    return Simulation(sc, times, truth, measurements, scheduled, covariances, info)


def _blocks(sim: Simulation) -> list[tuple[int, int]]:
    """(offset, runs) of the stages' blocks of runs (`stages.common.block_runs`)."""
    M, K = sim.runs, len(sim.times) - 1
    B = block_runs(K, M, None)
    return [(off, min(B, M - off)) for off in range(0, M, B)]


def estimate(
    scenario: Scenario | str | os.PathLike[str],
    sim: Simulation,
    architectures: Sequence[str] | str | None = None,
    *,
    filter: str | None = None,
    late: str | None = None,
) -> Estimates:
    """Each architecture's estimates of the runs (default: the scenario's `[estimate]
    architectures`; one name may be given as a string; an empty list is refused), as
    `fusionlog estimate` computes them: {name: `Estimate`} with `.mean` (M, K+1, n) and `.cov`
    (M, K+1, n, n). `scenario` is the filters' model: the one simulated, or another
    (`fusionlog estimate --model`), whose sensors are taken from `sim` by name; `filter`
    ("EKF" or "UKF") overrides its local filter as `--filter` does, `late` its policy for late
    measurements as `--late` does."""
    scenario = _state_scenario(scenario)
    _check_sim(sim)
    system = scenario.system
    if filter is not None:
        from .stages.state_kind import with_filter

        system = with_filter(system, filter, "filter")
    if late is not None:
        from .stages.state_kind import with_late

        system = with_late(system, late, "late")
    names = check_architecture_names(architectures)
    archs = check_architectures(names or list(scenario.architectures), system, "architectures")
    check_discretisable(
        system,
        sim.scenario,
        scenario.path or scenario.name,
        f"the simulation of {sim.scenario.name}",
    )
    z = sim.stacked(system)
    cache = PlanCache(
        sim.on_instants(system), len(sim.times) - 1, one_run=z.shape[0] == 1, clock=sim.times
    )
    cache.arrivals = sim.arrivals(system)
    parts: dict[str, list[BlockEstimate]] = {a: [] for a in archs}
    for off, n in _blocks(sim):
        block = estimate_block(cache.system, archs, z[off : off + n], cache=cache)
        for a, e in block.estimates.items():
            parts[a].append(e)
    out = Estimates({a: _joined(es) for a, es in parts.items()})
    out.provenance = cache.provenance() | {"late": system.late}  # the policy, for `evaluate`
    return out


def _check_sim(sim: Simulation) -> None:
    if not isinstance(sim, Simulation):
        raise ValidationError(
            f"sim: expected a Simulation (fusionlog.simulate), got {type(sim).__name__}"
        )
    sim.check()


def _joined(es: list[BlockEstimate]) -> Estimate:
    """One estimate of the blocks' runs (a covariance shared by every block stays shared)."""
    if len(es) == 1:
        return Estimate(es[0].mean, es[0].cov)
    mean = np.concatenate([e.mean for e in es])
    if all(e.shared_cov and e.cov is es[0].cov for e in es):
        return Estimate(mean, es[0].cov)
    covs = [e.cov if not e.shared_cov else np.broadcast_to(e.cov, e.mean.shape[:1] + e.cov.shape)
            for e in es]  # fmt: skip
    return Estimate(mean, np.concatenate(covs))


def evaluate(
    scenario: Scenario | str | os.PathLike[str], sim: Simulation, estimates: Estimates
) -> Evaluation:
    """MSE (eq. 45), ANEES, DM (eq. 47) with their exact expected values, NIS where it says
    something, and sample runs: what `fusionlog evaluate` puts in summary.json and the
    recording (written only by `Evaluation.save`). `scenario` is the model the estimates
    were made with (`estimate`); the truth is `sim`'s. `estimates` is {name: `Estimate`} of
    `sim`'s runs and instants, each (run, instant) an estimate (finite, its covariance
    positive semidefinite) or none (NaN in mean and cov): anything else is a
    ValidationError naming the architecture."""
    scenario = _state_scenario(scenario)
    _check_sim(sim)
    sc = sim.scenario  # the truth's: the runs, steps and seed simulated
    system = scenario.system
    late = getattr(estimates, "provenance", {}).get("late")
    if late is not None and isinstance(system, System):  # `estimate(late=)`: its policy
        system = dataclasses.replace(system, late=late)
    filter_sys, truth_sys = sim.on_instants(system), sim.on_instants(sc.system)
    _check_estimates(sim, estimates, filter_sys)
    # the estimates' record of their measurement pattern (plain dicts: none known, per run)
    prov = (
        estimates.provenance
        if isinstance(estimates, Estimates) and hasattr(estimates, "provenance")
        else {"measurement_pattern": "per-run"}
    )
    # the sensors' availability, where it says something (their own timing, a recording)
    timed = sc.replay is not None or any(not s.timing.default for s in sc.system.sensors)
    log = SensorLog(
        sim.truth is not None,
        sim.scheduled if timed else None,
        sim.truth_info,
        sim.arrivals(scenario.system),
    )
    ev = StateEvaluator(
        sc, list(estimates), filter_sys, truth_sys, sim.runs, sim.times, prov, log, sc.name
    )
    topics = {sensor_topic(name): z for name, z in sim.measurements.items()}
    for off, n in _blocks(sim):
        ests = {}
        for a, e in estimates.items():
            mean, cov = ests[estimates_topic(a)] = _runs(e, off, n)
            check_estimate_values(a, mean, cov, off)  # a shared cov: its (K+1, n, n)
        readings = {t: z[off : off + n] for t, z in topics.items()}
        truth = None if sim.truth is None else sim.truth[off : off + n]
        ev.add(off, truth, ests, readings)
    return Evaluation(**vars(ev.evaluation({"command": "fusionlog.evaluate"})))


def _check_estimates(sim: Simulation, estimates: Estimates, system: System) -> None:
    """The estimates are `Estimate`s of known architectures, of `sim`'s runs and instants and
    of the filter's states: one clear error, not numpy's deep inside."""
    if not isinstance(estimates, Mapping):
        raise ValidationError(
            f"estimates: expected {{architecture: Estimate}} (what fusionlog.estimate returns), "
            f"got {type(estimates).__name__}"
        )
    if not estimates:
        raise ValidationError("estimates: empty (fusionlog.estimate gives them)")
    names = check_architecture_names(list(estimates))
    check_architectures(names, system, "estimates")
    for a, e in estimates.items():
        if not isinstance(e, Estimate):
            raise ValidationError(
                f"estimates[{a!r}]: expected an Estimate (fusionlog.estimate returns them; "
                f"fusionlog.Estimate(mean, cov) makes one), got {type(e).__name__}"
            )
        check_estimate_shapes(a, e, sim.runs, len(sim.times), system.n)


def _runs(e: Estimate, off: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, cov) of runs [off, off + n) of an estimate, a shared covariance (K+1, n, n)
    once for the block (the evaluator's one inverse per instant for all runs)."""
    return e.mean[off : off + n], e._shared if e._shared is not None else e.cov[off : off + n]
