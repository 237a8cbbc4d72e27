"""`fusionlog run`: simulate (or import a replay's recorded data), estimate and evaluate into
one folder, the four outputs committed together or not at all."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fusionlog.driver import KeptPlans
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapWriter
from fusionlog.memory import release_freed_memory
from fusionlog.scenario import Scenario, check_budget

from .common import sha256_of
from .estimate import estimate_to
from .evaluate import evaluate_into
from .kinds import kind_of
from .simulate import simulate_to

#: The outputs of a run, in the order they are written.
RUN_OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")


@dataclass
class RunResult:
    scenario: Scenario  # as run (a replay: with its instants and runs from the data)
    summary: dict[str, Any]
    seconds: dict[str, float]  # per stage: simulate (or import), estimate, evaluate
    notes: list[str]  # what an import counted and reported


def run_pipeline(
    sc: Scenario,
    out_dir: Path,
    *,
    archs: list[str],
    filter_name: str | None = None,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog run",
    inputs: list[Path] | None = None,
) -> RunResult:
    """Simulate (a replay: import) `sc`, estimate with `archs` (empty: the scenario's own) and
    evaluate into RUN_OUTPUTS in `out_dir`. A run that fails half-way leaves the previous
    outputs as they were, not a mix."""
    outs = {k: Path(out_dir) / k for k in RUN_OUTPUTS}
    inputs = list(inputs or [])
    if sc.replay is not None:
        from .import_data import replay_inputs

        inputs += replay_inputs(sc)
    else:  # before the output folder is made: a run that cannot fit leaves nothing behind
        check_budget(sc, kind_of(sc.kind).bytes_per_run_step(sc), "simulating")
    seconds: dict[str, float] = {}
    notes: list[str] = []
    # the evaluation's exact analysis takes the estimate's per-run plans of the same block
    kept = KeptPlans()
    with Outputs(list(outs.values()), force=force, inputs=inputs) as o:
        t0 = time.perf_counter()
        if sc.replay is not None:
            from .import_data import import_to, read_replay  # the decoders: only replays need them

            data = read_replay(sc)
            sc, notes = data.scenario, data.notes
            origin = data.first_ns
            with McapWriter(o.open(outs["sensors.mcap"]), time_origin_ns=origin) as w:
                import_to(data, w, command=command)
            del data  # the imported readings are in sensors.mcap: not held through the stages
            seconds["import"] = time.perf_counter() - t0
        else:
            with McapWriter(o.open(outs["sensors.mcap"])) as w:
                simulate_to(sc, w, block=block, command=command)
            seconds["simulate"] = time.perf_counter() - t0
        release_freed_memory()
        t1 = time.perf_counter()
        # the scenario the sensors file records is `sc` (parsed once, by the caller) and its
        # digest is taken once: the estimate and evaluate steps do not read them again
        sensors = o.temp_path(outs["sensors.mcap"])
        digest = sha256_of(sensors)
        with McapWriter(o.open(outs["estimates.mcap"])) as w:
            estimate_to(
                sensors,
                w,
                archs=archs or list(sc.architectures),
                filter_name=filter_name,
                block=block,
                command=command,
                sensors_name="sensors.mcap",
                recorded=sc,
                sensors_sha256=digest,
                kept=kept,
            )
        seconds["estimate"] = time.perf_counter() - t1
        release_freed_memory()
        t2 = time.perf_counter()
        summary, _ = evaluate_into(
            o.temp_path(outs["sensors.mcap"]),
            o.temp_path(outs["estimates.mcap"]),
            o,
            outs["evaluation.rrd"],
            outs["summary.json"],
            block=block,
            scenario=sc,
            sensors_sha256=digest,
            estimates_name="estimates.mcap",
            kept=kept,
        )
        o.commit()
        seconds["evaluate"] = time.perf_counter() - t2
    return RunResult(sc, summary, seconds, notes)
