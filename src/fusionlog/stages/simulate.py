"""`fusionlog simulate`: a scenario's truth and sensor streams into an MCAP file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fusionlog.core.simulate import simulate
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapWriter
from fusionlog.scenario import Scenario

from .common import (
    PROVENANCE_META,
    SCENARIO_META,
    block_runs,
    progress,
    provenance,
    scenario_metadata,
)


@dataclass
class SimulateResult:
    path: Path
    runs: int
    steps: int
    messages: int


def run_simulate(
    scenario: Scenario,
    out: Path,
    *,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog simulate",
) -> SimulateResult:
    """Simulate `scenario` block by block of runs and write /truth and /sensors/<name>."""
    sys_ = scenario.system
    K, M = scenario.steps, scenario.runs
    B = block_runs(K, M, block)
    times = scenario.times  # the reader relies on exactly these (McapFile._recorded_structure)
    slices = sys_.sensor_slices
    topics = [f"/sensors/{s.name}" for s in sys_.sensors]
    messages = 0
    with Outputs([out], force=force) as outs, McapWriter(outs.open(out)) as w:
        w.add_metadata(SCENARIO_META, scenario_metadata(scenario))
        w.add_metadata(PROVENANCE_META, provenance(command, scenario.seed))
        offsets = range(0, M, B)
        for off in progress(offsets, len(offsets), "simulate"):
            runs = min(B, M - off)
            x, z = simulate(sys_, K, scenario.seed, off, runs)
            for k in range(K + 1):
                w.write_values("/truth", k, float(times[k]), off, x[:, k])
                for topic, sl in zip(topics, slices, strict=True):
                    w.write_values(topic, k, float(times[k]), off, z[:, k, sl])
            messages += (K + 1) * (1 + len(topics))
        w.close()
        outs.commit()
    return SimulateResult(Path(out), M, K, messages)
