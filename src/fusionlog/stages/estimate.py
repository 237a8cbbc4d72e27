"""`fusionlog estimate`: replay a sensors MCAP through fusion architectures."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusionlog.core.architectures import Plan, build_plan, estimate, run_plan, shared_pattern
from fusionlog.core.model import System
from fusionlog.core.names import parse_arch
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapFile, McapWriter
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
    if sc is not None and system.n != sc.system.n:
        raise FusionlogError(
            f"{model_path}: the model has {system.n} states, "
            f"the scenario recorded in {sensors_path} has {sc.system.n}"
        )
    if not archs:
        archs = list(sc.architectures) if sc is not None else ["CKF"]
    archs = check_architectures(archs, system, "--arch")
    if out.exists() and not force:
        raise FusionlogError(f"{out}: exists; use --force to overwrite")
    K, M = mf.steps() - 1, mf.runs()
    times = mf.times()
    B = block_runs(K, M, block)
    plans: dict[tuple[str, bytes], Plan] = {}
    meta_prov = provenance(
        command,
        sc.seed if sc is not None else None,
        sensors_sha256=sha256_of(Path(sensors_path)),
        sensors_file=Path(sensors_path).name,
        model_source=model_source,
        model=json.dumps(system_to_dict(system)),
        architectures=json.dumps(archs),
    )
    pattern: np.ndarray | None = None  # the measurement pattern shared by every run so far
    per_run = False
    outs = Outputs([out], force=force, inputs=[Path(sensors_path)])
    with outs, McapWriter(outs.open(out)) as w:
        if SCENARIO_META in mf.metadata:
            w.add_metadata(SCENARIO_META, mf.metadata[SCENARIO_META])
        blocks = mf.iter_run_blocks(topics, B)
        for off, _runs, data in progress(blocks, -(-M // B), "estimate"):
            z = np.concatenate([data[t] for t in topics], axis=-1)
            block_pattern = shared_pattern(z)
            if block_pattern is None or (pattern is not None and (block_pattern != pattern).any()):
                per_run = True
            elif pattern is None:
                pattern = block_pattern
            ests = {}
            for a in archs:
                if block_pattern is not None:
                    key = (a, np.packbits(block_pattern).tobytes())
                    if key not in plans:
                        mask = None if block_pattern.all() else block_pattern
                        plans[key] = build_plan(system, a, K, mask)
                    ests[a] = run_plan(plans[key], z)
                else:
                    ests[a] = estimate(system, z, a)
            # The documented order (for each step, for each topic) lets a reader learn every
            # topic from the first messages of the file.
            for k in range(K + 1):
                for a, est in ests.items():
                    cov = est.cov[k] if est.shared_cov else est.cov[:, k]
                    w.write_estimate(
                        f"/estimates/{a}", k, float(times[k]), off, est.mean[:, k], cov
                    )
        # Written last, when the pattern of the whole file is known; the evaluator's exact
        # analysis needs it (a shared pattern is analysed with the same mask, per-run is not).
        if per_run or pattern is None:
            meta_prov["measurement_pattern"] = "per-run"
        elif pattern.all():
            meta_prov["measurement_pattern"] = "complete"
        else:
            meta_prov["measurement_pattern"] = json.dumps(pattern.astype(int).tolist())
        w.add_metadata(PROVENANCE_META, meta_prov)
        w.close()
        outs.commit()
    return EstimateResult(Path(out), archs, M, K)
