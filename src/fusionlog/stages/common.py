"""Pieces the three stages share: block sizes, provenance, progress bars, loading a scenario
back out of a sensors file."""

from __future__ import annotations

import hashlib
import json
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

from tqdm import tqdm

from fusionlog import __version__
from fusionlog.core.model import System
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.scenario import Scenario, scenario_from_text, scenario_with

SCENARIO_META = "fusionlog.scenario"
PROVENANCE_META = "fusionlog.provenance"
RUN_STEPS_PER_BLOCK = 1 << 20

T = TypeVar("T")


def block_runs(steps: int, runs: int, requested: int | None = None) -> int:
    """Runs per block: about a million run-steps, so memory is set by the block, not by M."""
    if requested is not None:
        return max(1, min(requested, runs))
    return max(1, min(runs, RUN_STEPS_PER_BLOCK // (steps + 1)))


def progress(items: Iterable[T], total: int, desc: str) -> Iterator[T]:
    """A progress bar on a terminal, silence when stderr is piped or captured."""
    yield from tqdm(
        items, total=total, desc=desc, unit="block", disable=not sys.stderr.isatty(), leave=False
    )


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def provenance(command: str, seed: int | None, **extra: str) -> dict[str, str]:
    """Provenance record; no wall-clock time, so that same-seed outputs are identical."""
    out = {"fusionlog_version": __version__, "command": command}
    if seed is not None:
        out["seed"] = str(seed)
    out.update(extra)
    return out


def scenario_metadata(scenario: Scenario) -> dict[str, str]:
    """The `fusionlog.scenario` record: the TOML as written plus the values actually used."""
    from fusionlog.scenario import system_to_dict

    return {
        "toml": scenario.source,
        "name": scenario.name,
        "steps": str(scenario.steps),
        "runs": str(scenario.runs),
        "seed": str(scenario.seed),
        "dt": repr(scenario.dt),
        "system": json.dumps(system_to_dict(scenario.system)),
    }


def scenario_from_file(mf: McapFile) -> Scenario | None:
    """The scenario recorded in a sensors file, with the runs/steps/seed it was run with."""
    meta = mf.metadata.get(SCENARIO_META)
    if meta is None:
        return None
    try:
        sc = scenario_from_text(meta["toml"], source=f"{mf.path} (metadata {SCENARIO_META})")
        return scenario_with(
            sc, runs=int(meta["runs"]), steps=int(meta["steps"]), seed=int(meta["seed"])
        )
    except (KeyError, ValueError) as e:
        raise FusionlogError(f"{mf.path}: metadata {SCENARIO_META} is unreadable ({e})") from e


def system_from_file(mf: McapFile) -> System | None:
    sc = scenario_from_file(mf)
    return None if sc is None else sc.system


def open_evaluation_inputs(
    sensors_path: Path, estimates_path: Path, outputs: list[Path], force: bool
) -> tuple[McapFile, McapFile, dict[str, str]]:
    """What every evaluation checks first: outputs free (or --force), both files readable, the
    truth present, the estimates made from this very sensors file and of the same size.
    Returns the two files and the estimates' provenance record."""
    for p in outputs:
        if p.exists() and not force:
            raise FusionlogError(f"{p}: exists; use --force to overwrite")
    sens = McapFile(sensors_path)
    est = McapFile(estimates_path)
    if "/truth" not in sens.topics:
        raise FusionlogError(f"{sensors_path}: no /truth topic, nothing to evaluate against")
    prov = est.metadata.get(PROVENANCE_META, {})
    recorded = prov.get("sensors_sha256")
    if recorded is not None and recorded != sha256_of(Path(sensors_path)):
        raise FusionlogError(
            f"{estimates_path}: was estimated from another sensors file "
            f"({prov.get('sensors_file', '?')}, sha256 {recorded[:12]}...), not {sensors_path}"
        )
    if est.steps() != sens.steps() or est.runs() != sens.runs():
        raise FusionlogError(
            f"{estimates_path}: {est.runs()} runs x {est.steps()} steps do not match "
            f"{sensors_path} ({sens.runs()} x {sens.steps()})"
        )
    return sens, est, prov
