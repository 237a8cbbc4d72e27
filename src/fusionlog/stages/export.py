"""``fusionlog export``: one run's estimate (or truth) as a trajectory file other tools read
(TUM, KITTI, CSV: `io.trajectory_text`), on the recording's clock.

The positions are the scenario's position states (``[evaluate] position_states``, default the
states x, y, z that exist) in order as tx, ty, tz, the missing ones 0. The clock: each instant's
``log_time`` as the writer stamped it (the file's time origin, `McapFile.time_origin_ns`, plus
the instant's ``time`` in whole nanoseconds), so a replay's export carries the recording's
absolute times and a simulation's counts from 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.topics import ESTIMATES_PREFIX, TRUTH, arch_of, estimates_topic
from fusionlog.io.trajectory_text import FORMATS, csv_text, kitti_text, tum_text

from .common import block_runs, scenario_from_file

__all__ = ["ExportResult", "export_text", "run_export"]


@dataclass(frozen=True)
class ExportResult:
    path: Path
    rows: int  # instants written


def _one_run(mf: McapFile, topic: str, run: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Run `run`'s values (K+1, n) of a truth topic, or mean (K+1, n) and covariance
    (K+1, n, n) of an estimates topic, read block by block (one block held)."""
    size = block_runs(mf.steps(), mf.runs())
    for off, n, data in mf.iter_run_blocks([topic], size):
        if off <= run < off + n:
            d = data[topic]
            if isinstance(d, tuple):
                mean, cov = d
                return mean[run - off], cov if cov.ndim == 3 else cov[run - off]
            return d[run - off], None
    raise FusionlogError(f"{mf.path}: run {run} not found")  # pragma: no cover - runs() said so


def export_text(
    path: Path, fmt: str, *, arch: str | None = None, truth: bool = False, run: int | None = None
) -> tuple[str, int]:
    """The file's text and its number of rows (`run_export` writes it)."""
    if fmt not in FORMATS:
        raise FusionlogError(f"--format: unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    if truth == (arch is not None):
        raise FusionlogError(f"{path}: give --arch NAME (an estimate) or --truth, one of them")
    mf = McapFile(path)
    sc = scenario_from_file(mf)
    if sc is None or sc.kind != "state":
        raise FusionlogError(f"{path}: not a fusionlog state log (no scenario of states)")
    if truth:
        topic = TRUTH
        if topic not in mf.topics:
            est = any(t.startswith(ESTIMATES_PREFIX) for t in mf.topics)
            hint = ": it is an estimates file, export its sensors file's truth" if est else ""
            raise FusionlogError(f"{path}: no /truth topic{hint}")
    else:
        topic = estimates_topic(arch)
        if topic not in mf.topics:
            have = [arch_of(t) for t in mf.topics if t.startswith(ESTIMATES_PREFIX)]
            raise FusionlogError(
                f"{path}: no architecture {arch!r} (the file has: {', '.join(have) or 'none'})"
            )
    runs = mf.runs()
    run = 0 if run is None else int(run)
    if not 0 <= run < runs:
        raise FusionlogError(f"{path}: no run {run} (the file has runs 0..{runs - 1})")
    values, cov = _one_run(mf, topic, run)
    origin = mf.time_origin_ns()  # instant 0's absolute time (0 for a simulation)
    stamps = [origin + int(t) for t in np.rint(mf.times() * 1e9).astype(np.int64)]
    if fmt == "csv":
        std = None
        if cov is not None:
            std = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0, None))
        return csv_text(stamps, list(sc.state_names), values, std), values.shape[0]
    if sc.trajectory is None:
        raise FusionlogError(
            f"{path}: the scenario has no position states for --format {fmt} (name them in "
            "[evaluate] position_states; the default is the states x, y, z that exist)"
        )
    pos = np.zeros((values.shape[0], 3))
    idx = list(sc.trajectory.positions)
    pos[:, : len(idx)] = values[:, idx]
    text = tum_text(stamps, pos) if fmt == "tum" else kitti_text(pos)
    return text, text.count("\n")


def run_export(
    path: Path,
    out: Path,
    fmt: str,
    *,
    arch: str | None = None,
    truth: bool = False,
    run: int | None = None,
    force: bool = False,
) -> ExportResult:
    """Write the export of `path` into `out` (atomic, never over an input, no overwrite
    without `force`)."""
    with Outputs([Path(out)], force=force, inputs=[Path(path)]) as outs:
        text, rows = export_text(Path(path), fmt, arch=arch, truth=truth, run=run)
        outs.open(Path(out)).write(text.encode())
        outs.commit()
    return ExportResult(Path(out), rows)
