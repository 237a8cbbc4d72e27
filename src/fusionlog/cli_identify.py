"""`fusionlog identify`: the click command over `stages.identify_run` (kept out of cli.py,
which holds the pipeline's other commands)."""

from __future__ import annotations

from pathlib import Path

import click

PATH = click.Path(path_type=Path, dir_okay=False)


@click.command()
@click.argument("scenario", type=PATH)
@click.argument("sensors", type=PATH, required=False)
@click.option(
    "--param",
    "params",
    multiple=True,
    required=True,
    metavar="KEY",
    help="A dotted key of the scenario to estimate (sensors.<name>.R, model.n0, model.q, "
    "model.Q, correlations.0.cov, prior.cov). Repeatable.",
)
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
              help="TUNED.toml: the scenario with the identified values.")  # fmt: skip
@click.option("--report", type=click.Path(path_type=Path),
              help="REPORT.json: values, standard errors, given values, their cost.")  # fmt: skip
@click.option("--with-truth", is_flag=True, help="Add the truth's likelihood (the log's truth).")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
def identify(scenario, sensors, params, output, report, with_truth, force) -> None:
    """Noise (R, Q, n0, cross-covariances, the prior's) of SCENARIO.toml from the data by
    maximum likelihood: SENSORS.mcap, or a replay file's recordings, or the scenario
    simulated. Prints the values with standard errors and what the file's values cost."""
    from fusionlog.stages.identify_run import run_identify

    res = run_identify(
        scenario,
        sensors,
        list(params),
        output,
        report=report,
        with_truth=with_truth,
        force=force,
    )
    click.echo(res.table())
    click.echo(f"-> {output}" + (f", {report}" if report else ""))
