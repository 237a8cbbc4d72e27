"""Runs held in memory: a scenario's simulated runs or a replay's recorded readings (one run),
in the stages' blocks of runs, and the estimates of architectures on them.

What the Python API (`fusionlog.api`, an adapter over this) and `fusionlog identify` work on:
`simulation_of` is the simulate stage's hook (the random streams belong to chunks of runs, so
the runs are those `fusionlog simulate` writes), `estimate_blocks` is `driver.estimate_block`
in the estimate stage's blocks of runs with one plan cache.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import numpy as np

from fusionlog.arguments import check_simulation
from fusionlog.core.architectures import Estimate as BlockEstimate
from fusionlog.core.model import System
from fusionlog.driver import PlanCache, estimate_block
from fusionlog.errors import FusionlogError, ValidationError
from fusionlog.scenario import Scenario, load_scenario, scenario_with
from fusionlog.scenario.scenario_base import memory_shortfall

from .common import block_runs
from .kinds import kind_of
from .noise import with_covariances

__all__ = ["Simulation", "blocks_of", "estimate_blocks", "simulation_of", "state_scenario",
           "with_arrivals"]  # fmt: skip


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


def state_scenario(scenario: Scenario | str | os.PathLike[str]) -> Scenario:
    """A loaded scenario, or the one of a file (`load_scenario`), of the state kind."""
    if isinstance(scenario, str | os.PathLike):
        scenario = load_scenario(scenario)
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


def simulation_of(
    scenario: Scenario, runs: int | None, seed: int | None, steps: int | None
) -> Simulation:
    """`runs` runs of K = `steps` steps with `seed` of a state scenario (each None: the
    scenario's), all held in memory; a replay's recorded readings as one run."""
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


def _recorded(scenario: Scenario) -> Simulation:
    """A replay's readings on their instants (what `fusionlog import` writes), as one run."""
    from .import_data import read_replay  # the decoders: only replays need them

    data = read_replay(scenario)
    sc = data.scenario
    K1, n = data.count, sc.system.n
    measurements, scheduled, covariances, arrival = {}, {}, {}, {}
    for sen, r in zip(sc.system.sensors, data.sensors, strict=True):
        if r.arrival:  # arrival = "log_time": when each reading was logged
            arrival[sen.name] = np.full((1, K1), np.nan)
        measurements[sen.name] = np.full((1, K1, sen.dim), np.nan)
        scheduled[sen.name] = np.zeros(K1, dtype=bool)
        if r.fill is not None:
            covariances[sen.name] = np.full((K1, sen.dim, sen.dim), np.nan)
    truth = np.full((1, K1, n), np.nan) if data.truth_rows is not None else None
    times = np.empty(K1)
    for win in data.windows():
        k = win.k0
        times[k : k + len(win.instants)] = (win.instants - data.first_ns) / 1e9
        for sen, (at, values, cov, arrival_ns) in zip(sc.system.sensors, win.sensors, strict=True):
            measurements[sen.name][0, k + at] = values
            scheduled[sen.name][k + at] = True
            if cov is not None:
                covariances[sen.name][k + at] = cov
            if arrival_ns is not None:
                arrival[sen.name][0, k + at] = (arrival_ns - data.first_ns) / 1e9
        if win.truth is not None:
            truth[0, k + win.truth[0]] = win.truth[1]
    info = data.truth_info or None
    sim = Simulation(sc, times, truth, measurements, scheduled, covariances, info)
    sim.arrival = arrival
    return sim


def with_arrivals(system: System, sim: Simulation) -> System:
    """The filters' model with the latency a replay's import found for its sensors with
    ``arrival = "log_time"`` (the range of their delays, in `sim.scenario`): the model as
    loaded has none, the delays being in the data."""
    if sim.scenario.replay is None or not sim.arrival:
        return system
    found = {s.name: s.timing for s in sim.scenario.system.sensors if s.name in sim.arrival}
    sensors = tuple(
        dataclasses.replace(s, timing=found[s.name]) if s.name in found else s
        for s in system.sensors
    )
    return dataclasses.replace(system, sensors=sensors)


def blocks_of(sim: Simulation) -> list[tuple[int, int]]:
    """(offset, runs) of the stages' blocks of runs (`stages.common.block_runs`)."""
    M, K = sim.runs, len(sim.times) - 1
    B = block_runs(K, M, None)
    return [(off, min(B, M - off)) for off in range(0, M, B)]


def estimate_blocks(
    system: System, sim: Simulation, archs: list[str]
) -> tuple[dict[str, list[BlockEstimate]], dict[str, str]]:
    """Each architecture's estimates of `sim`'s runs by the filters' model `system` (its
    sensors' readings taken from `sim` by name), one per block of runs (`blocks_of`), and the
    record of their measurement pattern (`PlanCache.provenance`)."""
    z = sim.stacked(system)
    cache = PlanCache(
        sim.on_instants(system), len(sim.times) - 1, one_run=z.shape[0] == 1, clock=sim.times
    )
    cache.arrivals = sim.arrivals(system)
    parts: dict[str, list[BlockEstimate]] = {a: [] for a in archs}
    for off, n in blocks_of(sim):
        block = estimate_block(cache.system, archs, z[off : off + n], cache=cache)
        for a, e in block.estimates.items():
            parts[a].append(e)
    return parts, cache.provenance()
