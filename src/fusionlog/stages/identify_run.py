"""``fusionlog identify`` as a command: its data (a sensors log, a replay's recordings, or the
scenario simulated), the identification (`identify.identify`) and its outputs, TUNED.toml and
REPORT.json, committed together (`io.atomic.Outputs`)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.topics import TRUTH, sensor_topic
from fusionlog.jsonout import dumps
from fusionlog.scenario import Scenario, load_scenario, scenario_from_doc

from . import identify_params as ip
from .common import SCENARIO_META, scenario_from_file
from .identify import Identification, identify
from .simulation import Simulation, simulation_of

__all__ = ["log_simulation", "run_identify"]


def log_simulation(path: Path, sc: Scenario) -> Simulation:
    """The runs of a sensors log (`fusionlog simulate` or `import`) as a `Simulation`:
    the readings of `sc`'s sensors by name, the truth where the log has it, each message's
    covariance where a one-run log's messages carry one."""
    mf = McapFile(path)
    recorded = scenario_from_file(mf)
    names = [s.name for s in sc.system.sensors]
    topics = [sensor_topic(n) for n in names]
    missing = [t for t in topics if t not in mf.topics]
    if missing:
        have = ", ".join(sorted(mf.topics)) or "none"
        raise FusionlogError(f"{path}: no topic {missing[0]} (topics: {have})")
    with_truth = TRUTH in mf.topics
    data = mf.read_all(topics + ([TRUTH] if with_truth else []))
    covs = mf.message_covariances_of(topics)
    meta = mf.metadata.get(SCENARIO_META, {})
    info = json.loads(meta["replay_truth"]) if "replay_truth" in meta else None
    return Simulation(
        recorded or sc,
        mf.times(),
        data[TRUTH] if with_truth else None,
        {n: data[t] for n, t in zip(names, topics, strict=True)},
        covariances={
            n: c for n, t in zip(names, topics, strict=True) if (c := covs.get(t)) is not None
        },  # fmt: skip
        truth_info=info,
    )


def run_identify(
    scenario: Path,
    sensors: Path | None,
    params: list[str],
    out: Path,
    *,
    report: Path | None = None,
    with_truth: bool = False,
    force: bool = False,
) -> Identification:
    """Identify `params` of `scenario` from `sensors` (default: a replay's recordings, or the
    scenario simulated with its runs and seed) and write TUNED.toml `out` (the scenario's text
    with the values in place; a replay's sources made relative to `out`'s folder) and REPORT
    `report`: all or nothing."""
    targets = [Path(out)] + ([Path(report)] if report else [])
    inputs = [Path(scenario)] + ([Path(sensors)] if sensors else [])
    with Outputs(targets, force=force, inputs=inputs) as outs:
        sc = load_scenario(scenario)
        if sc.kind != "state":
            raise FusionlogError(f"{scenario}: identify estimates the noise of state scenarios")
        if sensors is not None:
            sim = log_simulation(Path(sensors), sc)
        else:
            sim = simulation_of(sc, None, None, None)
        result = identify(sc, sim, params, with_truth=with_truth)
        text = result.toml
        if sc.replay is not None:
            text = _moved(sc, result, out)
        outs.open(Path(out)).write(text.encode())
        if report is not None:
            outs.open(Path(report)).write((dumps(result.report, indent=2) + "\n").encode())
        outs.commit()
    return result


def _moved(sc: Scenario, result: Identification, out: Path) -> str:
    """The tuned replay's text with its sources relative to the output's folder."""
    from fusionlog.scenario import toml

    file = str(sc.path)
    doc = toml.parse_toml(sc.source, file)
    plist = ip.params_of(doc, result.keys, file)
    values = [np.asarray(result.values[k], dtype=float) for k in result.keys]
    src = os.path.dirname(os.path.abspath(file))
    dst = os.path.dirname(os.path.abspath(out))
    text = ip.written_back(sc.source, doc, plist, values, file, src, dst)
    scenario_from_doc(toml.parse_toml(text, str(out)), str(out), text, str(out))
    return text
