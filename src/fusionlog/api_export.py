"""``fusionlog.export``: the Python API of ``fusionlog export`` (DESIGN.md "Trajectory metrics")."""

from __future__ import annotations

import os

from .errors import FusionlogError

__all__ = ["export"]


def export(
    log: str | os.PathLike[str],
    output: str | os.PathLike[str] | None = None,
    *,
    arch: str | None = None,
    truth: bool = False,
    run: int | None = None,
    format: str = "tum",
    force: bool = False,
) -> str:
    """One run's estimate (`arch`, of an estimates MCAP) or truth (`truth=True`, of a sensors
    MCAP) as the text of a trajectory file: ``format`` "tum" (time tx ty tz qx qy qz qw, the
    position states as tx, ty, tz, identity orientation), "kitti" (3 × 4 poses, row-major) or
    "csv" (time and every state with its standard deviation), on the recording's clock.
    Written to `output` only when given (atomic; an existing file only with `force`)."""
    from pathlib import Path

    from .io.trajectory_text import FORMATS
    from .stages.export import export_text, run_export

    if format not in FORMATS:
        raise FusionlogError(f"format: unknown format {format!r} (known: {', '.join(FORMATS)})")
    if run is not None and (isinstance(run, bool) or not isinstance(run, int) or run < 0):
        raise FusionlogError(f"run: expected an integer >= 0, got {run!r}")
    if arch is not None and not isinstance(arch, str):
        raise FusionlogError(f"arch: expected an architecture name, got {arch!r}")
    if output is not None:
        run_export(Path(log), Path(output), format, arch=arch, truth=truth, run=run, force=force)
        return Path(output).read_text()
    return export_text(Path(log), format, arch=arch, truth=truth, run=run)[0]
