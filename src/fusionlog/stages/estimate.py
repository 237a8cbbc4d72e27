"""`fusionlog estimate`: replay a sensors MCAP through fusion architectures."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusionlog.core.architectures import Plan, build_plan, estimate, run_plan
from fusionlog.core.model import System
from fusionlog.core.names import parse_arch
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap_io import McapFile, McapWriter
from fusionlog.scenario import load_model, system_to_dict

from .common import (
    PROVENANCE_META,
    SCENARIO_META,
    block_runs,
    progress,
    provenance,
    scenario_from_file,
    sha256_of,
)


@dataclass
class EstimateResult:
    path: Path
    architectures: list[str]
    runs: int
    steps: int


def resolve_model(sensors: McapFile, model_path: Path | None) -> tuple[System, str]:
    """The filter model: `--model` if given, else the scenario recorded in the sensors file."""
    if model_path is not None:
        return load_model(model_path), str(model_path)
    sc = scenario_from_file(sensors)
    if sc is None:
        raise FusionlogError(
            f"{sensors.path}: no {SCENARIO_META} metadata to take the model from; "
            "pass --model MODEL.toml"
        )
    return sc.system, "scenario"


def _check_topics(mf: McapFile, system: System) -> list[str]:
    topics = []
    for s in system.sensors:
        t = f"/sensors/{s.name}"
        if t not in mf.topics:
            have = ", ".join(sorted(mf.topics)) or "none"
            raise FusionlogError(
                f"{mf.path}: no topic {t} for sensor {s.name!r} of the model (topics: {have})"
            )
        if mf.dim_of(t) != s.dim:
            raise FusionlogError(
                f"{mf.path}: topic {t} has {mf.dim_of(t)} values per step, "
                f"the model's sensor {s.name!r} has {s.dim}"
            )
        topics.append(t)
    return topics


def check_architectures(names: list[str], system: System, where: str) -> list[str]:
    for a in names:
        try:
            parse_arch(a, [s.name for s in system.sensors])
        except ValueError as e:
            raise FusionlogError(f"{where}: {e}") from e
    return list(dict.fromkeys(names))


def run_estimate(
    sensors_path: Path,
    out: Path,
    *,
    archs: list[str] | None = None,
    model_path: Path | None = None,
    force: bool = False,
    block: int | None = None,
    command: str = "fusionlog estimate",
) -> EstimateResult:
    """Estimate every run of `sensors_path` with each architecture; write /estimates/<ARCH>."""
    mf = McapFile(sensors_path)
    system, model_source = resolve_model(mf, model_path)
    topics = _check_topics(mf, system)
    sc = scenario_from_file(mf)
    if not archs:
        archs = list(sc.architectures) if sc is not None else ["CKF"]
    archs = check_architectures(archs, system, "--arch")
    if out.exists() and not force:
        raise FusionlogError(f"{out}: exists; use --force to overwrite")
    K, M = mf.steps() - 1, mf.runs()
    times = mf.times()
    B = block_runs(K, M, block)
    plans: dict[str, Plan] = {}
    meta_prov = provenance(
        command,
        sc.seed if sc is not None else None,
        sensors_sha256=sha256_of(Path(sensors_path)),
        sensors_file=Path(sensors_path).name,
        model_source=model_source,
        model=json.dumps(system_to_dict(system)),
        architectures=json.dumps(archs),
    )
    with McapWriter(out, force=force) as w:
        if SCENARIO_META in mf.metadata:
            w.add_metadata(SCENARIO_META, mf.metadata[SCENARIO_META])
        w.add_metadata(PROVENANCE_META, meta_prov)
        blocks = mf.iter_run_blocks(topics, B)
        for off, _runs, data in progress(blocks, -(-M // B), "estimate"):
            z = np.concatenate([data[t] for t in topics], axis=-1)
            shared = not np.isnan(z).any()
            for a in archs:
                if shared:
                    if a not in plans:
                        plans[a] = build_plan(system, a, K)
                    est = run_plan(plans[a], z)
                else:
                    est = estimate(system, z, a)
                topic = f"/estimates/{a}"
                for k in range(K + 1):
                    cov = est.cov[k] if est.shared_cov else est.cov[:, k]
                    w.write_estimate(topic, k, float(times[k]), off, est.mean[:, k], cov)
    return EstimateResult(Path(out), archs, M, K)
