"""The CLI of the trajectory metrics (DESIGN.md "Trajectory metrics"): ``--align`` (on
``evaluate`` and ``run``) and ``fusionlog export``. Thin click adapters, registered on the
``fusionlog`` group by :mod:`fusionlog.cli`."""

from __future__ import annotations

from pathlib import Path

import click

__all__ = ["align_option", "export"]

align_option = click.option(
    "--align",
    type=click.Choice(["none", "origin", "rigid", "similarity"]),
    help="Align each estimate's positions onto the truth before APE/RPE "
    "(overrides [evaluate] align).",
)


@click.command()
@click.argument("log", metavar="ESTIMATES.mcap|SENSORS.mcap", type=click.Path(path_type=Path))
@click.option("--arch", help="The architecture whose estimate to export.")
@click.option("--truth", is_flag=True, help="Export the truth of a sensors file instead.")
@click.option("--run", type=click.IntRange(min=0), help="Which run (default 0).")
@click.option("--format", "fmt", type=click.Choice(["tum", "kitti", "csv"]), required=True,
              help="tum: t tx ty tz qx qy qz qw; kitti: 3x4 poses; csv: states, std.")  # fmt: skip
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="The file to write.")  # fmt: skip
@click.option("--force", is_flag=True, help="Overwrite an existing output.")
def export(log, arch, truth, run, fmt, output, force) -> None:
    """One run's estimate (--arch) or truth (--truth) as a trajectory file other tools read
    (evo, rpg_trajectory_evaluation, a spreadsheet), on the recording's clock."""
    from fusionlog.stages.export import run_export

    res = run_export(log, output, fmt, arch=arch, truth=truth, run=run, force=force)
    click.echo(f"{res.path}: {res.rows} rows ({fmt})")
