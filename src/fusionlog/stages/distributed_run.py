"""``fusionlog run --workers N | --scheduler ADDRESS``: one big scenario's runs on Dask.

The runs are split into blocks (:func:`.montecarlo.blocks`) that workers simulate, estimate and
reduce to metric sums; no sensor or estimate log is written (it would carry every estimate back
to this process: 10^7 runs of the paper's example are 3.4 GB of means per architecture), so a
distributed run writes ``evaluation.rrd`` and ``summary.json`` only, committed together.

Both come from the state kind's own Evaluator, as in ``fusionlog run``: the first few runs (the
sample runs and the state-plane points of the recording) are computed here and added to it as
a block of estimates, the workers' sums of the other runs are merged into its accumulators in
block order, and its summary (the exact analysis beside the Monte Carlo values) and recording
follow. The runs are those of ``fusionlog run`` with the same seed, so the numbers agree with it
to rounding (the sums are added in another order).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.driver import pattern_record
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import estimates_topic, sensor_topic
from fusionlog.jsonout import dumps
from fusionlog.scenario import Scenario

from .common import provenance
from .distributed import CONNECT_TIMEOUT, executor
from .evaluator import SensorLog, StateEvaluator
from .kinds import kind_of
from .montecarlo import (
    Job,
    block_estimates,
    block_sums,
    blocks,
    exact_mask,
    fold,
    simulated_readings,
)
from .state_kind import with_filter

__all__ = ["DISTRIBUTED_OUTPUTS", "DistributedRun", "run_distributed"]

#: What a distributed run writes in its folder (no MCAP logs: see the module docstring).
DISTRIBUTED_OUTPUTS = ("evaluation.rrd", "summary.json")
#: Runs computed here for the recording's state-plane view (`evaluator.views_part.PLANE_POINTS`).
PLANE_RUNS = 300


@dataclass
class DistributedRun:
    out_dir: Path
    summary: dict[str, Any]
    executor: str
    seconds: float


def _remote_blocks(scenario: Scenario, local: int, block: int | None) -> list[tuple[int, int]]:
    """The blocks after the `local` runs computed here: the scenario's blocks, the first one
    starting at `local` (a function of the scenario alone, whatever the cluster)."""
    out = []
    for off, n in blocks(scenario, block):
        end = off + n
        if end > local:
            out.append((max(off, local), end - max(off, local)))
    return out


def run_distributed(
    scenario: Scenario,
    out_dir: Path,
    *,
    archs: Sequence[str] = (),
    workers: int | None = None,
    scheduler: str | None = None,
    scheduler_timeout: float = CONNECT_TIMEOUT,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog run",
    filter_name: str | None = None,
) -> DistributedRun:
    """Evaluate every run of `scenario` on Dask into ``out_dir/evaluation.rrd`` and
    ``out_dir/summary.json`` (both or neither). `workers` N: a LocalCluster of N processes
    (0: this process); `scheduler`: a running cluster; neither: one process per CPU.
    `filter_name` (--filter) sets the local filter."""
    sc = scenario
    if filter_name is not None:
        sc = dataclasses.replace(sc, system=with_filter(sc.system, filter_name))
    if sc.kind != "state":
        raise FusionlogError(
            f"{sc.path or sc.name}: --workers/--scheduler run state scenarios; "
            f"a {sc.kind} scenario runs in one process (without them)"
        )
    if sc.replay is not None:  # the workers simulate runs: a recorded log has one, not theirs
        raise FusionlogError(
            f"{sc.path or sc.name}: a replay is one recorded run, there is nothing to spread "
            "over workers: run it without --workers/--scheduler"
        )
    kind = kind_of(sc.kind)
    archs = kind.check_architectures(list(archs) or list(sc.architectures), sc.system, "--arch")
    targets = [Path(out_dir) / name for name in DISTRIBUTED_OUTPUTS]
    inputs = [Path(sc.path)] if sc.path else []
    # runs whose patterns differ (dropouts): the workers also sum each run's exact statistics
    job = Job(sc, tuple(archs), uuid.uuid4().hex, not exact_mask(sc)[0])
    local = min(sc.runs, max(sc.sample_runs, PLANE_RUNS if sc.plane_view else 0, 1))
    remote = _remote_blocks(sc, local, block)
    t0 = time.perf_counter()
    ex = executor(workers, scheduler, timeout=scheduler_timeout)  # the address checked first
    with Outputs(targets, force=force, inputs=inputs) as outs, ex:
        totals: dict[str, Any] = {}  # arch -> the workers' sums, merged in block order
        conditional: dict[str, Any] = {}  # arch -> their conditional expected sums
        trajectory: dict[str, Any] = {}  # arch -> their APE/RPE sums
        patterns: set[bytes | None] = set()  # the blocks' shared patterns (two: per-run)
        with contextlib.closing(
            ex.map([(block_sums, (job, off, n)) for off, n in remote], "run")
        ) as results:
            # the sample runs here while the workers start on the rest
            x, z, est, pattern = block_estimates(job, 0, local, plans=ex.plans)
            patterns.add(None if pattern is None else np.packbits(pattern).tobytes())
            for s in results:
                fold(totals, s, conditional, trajectory)
                if len(patterns) < 2:
                    patterns.add(s.pattern)
        ex.release()  # the cluster closes while the summary and the recording are made
        prov = provenance(
            command,
            sc.seed,
            model_source="scenario",
            architectures=json.dumps(archs),
            runs_on=ex.description,
            **pattern_record(sorted(patterns, key=repr), (sc.instants, sc.system.m)),
        )
        system = sc.system.on_times(sc.times)
        log = SensorLog(arrivals=kind.arrivals(sc, 0, local))  # late sample runs' arrivals
        ev = StateEvaluator(sc, archs, system, system, sc.runs, sc.times, prov, log, sc.name)
        readings = {sensor_topic(s.name): z[..., sl] for s, sl in zip(
            system.sensors, system.sensor_slices, strict=True)}  # fmt: skip
        ev.add(0, x, {estimates_topic(a): (e.mean, e.cov) for a, e in est.items()}, readings)
        # the workers' sums of the other runs (and, for per-run patterns, their runs' exact
        # sums: the evaluator's own are the sample runs')
        ev.merge(totals, conditional, trajectory)
        if not system.linear:  # the PCRB of the workers' runs: their truth, simulated here
            for off, n in remote:
                ev.add_bound(*simulated_readings(sc, off, n))
        evaluation = ev.evaluation(prov)
        summary = evaluation.summary
        text = dumps(summary, indent=2) + "\n"  # before the recording, as evaluate does
        kind.write_evaluation(outs.open(targets[0]), evaluation)
        outs.open(targets[1]).write(text.encode())
        outs.commit()
    return DistributedRun(Path(out_dir), summary, ex.description, time.perf_counter() - t0)
