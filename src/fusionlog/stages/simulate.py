"""`fusionlog simulate`: a scenario's truth and sensor streams into an MCAP file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusionlog.driver.long_log import time_block
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import VALUES, McapWriter
from fusionlog.io.mcap.run_steps import RunColumn
from fusionlog.io.mcap.topics import TRUTH, sensor_topic
from fusionlog.scenario import Scenario, check_budget

from .common import (
    PROVENANCE_META,
    SCENARIO_META,
    block_runs,
    progress,
    provenance,
    scenario_metadata,
)
from .kinds import kind_of


@dataclass
class SimulateResult:
    path: Path
    runs: int
    steps: int
    messages: int


def simulate_to(
    scenario: Scenario, w: McapWriter, *, block: int | None = None, command: str
) -> int:
    """Simulate `scenario` block by block of runs into an open writer; returns the message
    count. /truth and /sensors/<name> get one message per step per block of runs."""
    kind = kind_of(scenario.kind)
    K, M = scenario.instants - 1, scenario.runs
    check_budget(scenario, kind.bytes_per_run_step(scenario), "simulating")
    B = block_runs(K, M, block)
    times = scenario.times  # the reader relies on exactly these
    topics = [sensor_topic(name) for name in kind.sensor_names(scenario.system)]
    # A sensor's topic has a message only at the instants it measures (its own rate).
    measures = scenario.schedule.measures
    if measures.shape[1] != len(topics):  # a kind without sensor timing: every instant
        measures = np.ones((K + 1, len(topics)), dtype=bool)
    w.add_metadata(SCENARIO_META, scenario_metadata(scenario, kind.system_fields(scenario)))
    w.add_metadata(PROVENANCE_META, provenance(command, scenario.seed))
    # fixed latencies: each reading's arrival is its time plus its sensor's latency
    lat = kind.latencies(scenario)
    # drawn delays of a long one-run log: drawn block by block (None: fixed, or several runs)
    drawn = kind.arrival_blocks(scenario, time_block()) if M == 1 else None
    late_sensors = lat is not None or drawn is not None or kind.arrivals(scenario, 0, 1) is not None
    if late_sensors:  # late sensors: the schema says arrival
        w.declare_arrival()
    every = list(range(len(topics)))
    # the sensors measuring at each instant, made for one instant at a time (a list per
    # instant is ~100 bytes: 0.4 GB for 4*10^6 instants)
    everywhere = bool(measures.all())
    blocks = None
    if not late_sensors or lat is not None or drawn is not None:
        blocks = kind.simulate_blocks(scenario, time_block())
    for k0, k1, x, z in blocks or ():  # one long run in blocks of time: a window at once
        arrival = next(drawn) if drawn is not None else None
        _block_messages(w, k0, times[k0:k1], x, z, topics, measures[k0:k1], lat, arrival)
    if blocks is not None:
        return (K + 1) + int(measures.sum())
    messages = 0
    offsets = range(0, M, B)
    for off in progress(offsets, len(offsets), "simulate"):
        runs = min(B, M - off)
        x, z = kind.simulate(scenario, off, runs)
        # late sensors: when each reading arrives (one value where every run's is the same)
        arrival = kind.arrivals(scenario, off, runs)
        late = [] if arrival is None else [j for j, s in enumerate(scenario.system.sensors)
                                           if s.timing.late]  # fmt: skip
        for k in range(K + 1):
            t = float(times[k])
            w.write_values(TRUTH, k, t, off, x[:, k])
            for j in every if everywhere else np.flatnonzero(measures[k]).tolist():
                a = None
                if j in late:
                    a = arrival[:, k, j]  # type: ignore[index]
                    a = a[:1] if (a == a[0]).all() else a
                w.write_values(topics[j], k, t, off, z[j][:, k], arrival=a)
        messages += (K + 1) + int(measures.sum())
    return messages


def _block_messages(w, k0, times, x, z, topics, measures, lat, arrival=None) -> None:
    """The block of a one-run log from instant k0 (`times` (w,), `measures` (w, S) the sensors
    measuring): the messages of the whole run's loop (`simulate_to`) written a window at once
    (`McapWriter.write_run_steps`: the same bytes), the truth at every instant, a sensor at
    the instants it measures, a late sensor's arrival t + its fixed latency `lat` (S,) s as
    there (`core.late_policy.draw_arrivals`), or with delays drawn the block's `arrival` (w, S)
    s of its late sensors (`core.late_policy.arrival_blocks`)."""
    columns = [RunColumn(TRUTH, VALUES, x[0])]
    for j, topic in enumerate(topics):
        a = None
        if arrival is not None and not np.isnan(arrival[0, j]):
            a = arrival[:, j]  # a sensor on time has none (NaN)
        elif lat is not None and lat[j] > 0.0:
            a = times + lat[j]
        columns.append(RunColumn(topic, VALUES, z[j][0], arrival=a))
    present = None
    if not measures.all():
        present = np.concatenate([np.ones((len(times), 1), bool), measures], axis=1)
    w.write_run_steps(k0, times, columns, present)


def run_simulate(
    scenario: Scenario,
    out: Path,
    *,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog simulate",
) -> SimulateResult:
    """Simulate `scenario` into the sensors file `out` (committed only when complete)."""
    out = Path(out)
    if scenario.replay is not None:  # its model and prior alone would simulate one instant
        raise FusionlogError(
            f"{scenario.path or scenario.name}: a replay file: its readings are recorded, not "
            f"simulated (`fusionlog import` writes them as a sensors file)"
        )
    inputs = [Path(scenario.path)] if scenario.path else []
    with Outputs([out], force=force, inputs=inputs) as outs:
        with McapWriter(outs.open(out)) as w:
            messages = simulate_to(scenario, w, block=block, command=command)
        outs.commit()
    return SimulateResult(out, scenario.runs, scenario.instants - 1, messages)
