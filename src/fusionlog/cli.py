"""The `fusionlog` command line: a thin click layer over `fusionlog.stages`.

Exit codes: 0 success, 1 a comparison found a regression, 2 bad usage or bad input (one line on
stderr naming the file and the problem; a traceback only with --debug), 130 interrupted.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import click

from fusionlog import __version__
from fusionlog.errors import DamagedFile, FusionlogError, OutputExists

PATH = click.Path(path_type=Path, dir_okay=False)


class _Group(click.Group):
    """Turns FusionlogError into one line and exit code 2, and Ctrl-C into exit code 130."""

    def invoke(self, ctx: click.Context) -> Any:
        debug = bool(ctx.params.get("debug"))
        try:
            return super().invoke(ctx)
        except FusionlogError as e:
            if debug:
                raise
            hint = ""
            if isinstance(e, DamagedFile) and e.path is not None:
                hint = f"; `fusionlog inspect --recover {e.path}` shows what is still readable"
            elif isinstance(e, OutputExists):
                hint = "; use --force to overwrite"
            click.echo(f"fusionlog: error: {e}{hint}", err=True)
            ctx.exit(2)
        except KeyboardInterrupt:
            if debug:
                raise
            click.echo("fusionlog: interrupted; no partial output was left behind", err=True)
            ctx.exit(130)


def _command_line() -> str:
    return " ".join(["fusionlog", *sys.argv[1:]])


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="fusionlog")
@click.option("--debug", is_flag=True, help="Show tracebacks instead of one-line errors.")
def main(debug: bool) -> None:
    """Simulate multi-sensor linear Gaussian systems to MCAP, replay them through fusion
    architectures, and evaluate the estimates into Rerun recordings."""


def _scenario(path: Path, runs: int | None, steps: int | None, seed: int | None):
    """The scenario: an identity scenario if the file has [identity], else a state one."""
    from fusionlog.stages.identity import is_identity_scenario_file, load_identity_scenario

    if is_identity_scenario_file(path):
        return load_identity_scenario(path, runs=runs, steps=steps, seed=seed)
    from fusionlog.scenario import load_scenario

    return load_scenario(path, runs=runs, steps=steps, seed=seed)


def _is_identity(scenario: Any) -> bool:
    return getattr(scenario, "kind", None) == "identity"


def _identity_log(path: Path, model: Path | None = None) -> bool:
    """Whether a sensors file (or, without scenario metadata, the --model) is identity."""
    from fusionlog.stages.identity import is_identity_file, is_identity_scenario_file

    return is_identity_file(path) or (model is not None and is_identity_scenario_file(model))


_runs = click.option("--runs", type=int, help="Monte Carlo runs M (overrides the scenario).")
_steps = click.option("--steps", type=int, help="Last instant K, k = 0..K (overrides).")
_seed = click.option("--seed", type=int, help="Random seed (overrides the scenario).")
_force = click.option("--force", is_flag=True, help="Overwrite existing outputs.")
_block = click.option(
    "--block-runs", type=click.IntRange(min=1), help="Runs per block (memory bound).", hidden=True
)
_arch = click.option(
    "--arch",
    "archs",
    multiple=True,
    help="Architecture (repeatable): CKF, HKF, MSC, MSC-GMF, SKF[:sensor], CI, FBS; "
    "BAYES, DS for identity scenarios.",
)


@main.command()
@click.argument("scenario", type=PATH)
@click.option("-o", "--output", type=PATH, required=True, help="Sensors MCAP file to write.")
@_runs
@_steps
@_seed
@_force
@_block
def simulate(scenario, output, runs, steps, seed, force, block_runs) -> None:
    """Simulate SCENARIO.toml: truth and sensor streams into an MCAP file."""
    sc = _scenario(scenario, runs, steps, seed)
    if _is_identity(sc):
        from fusionlog.stages.identity import run_simulate
    else:
        from fusionlog.stages.simulate import run_simulate

    res = run_simulate(sc, output, force=force, block=block_runs, command=_command_line())
    click.echo(f"{res.path}: {res.runs} runs x {res.steps + 1} steps, {res.messages} messages")


@main.command()
@click.argument("sensors", type=PATH)
@click.option("-o", "--output", type=PATH, required=True, help="Estimates MCAP file to write.")
@_arch
@click.option("--model", type=PATH, help="Filter model TOML replacing the recorded scenario's.")
@_force
@_block
def estimate(sensors, output, archs, model, force, block_runs) -> None:
    """Replay SENSORS.mcap through fusion architectures into an estimates MCAP file."""
    if _identity_log(sensors, model):
        from fusionlog.stages.identity import run_estimate
    else:
        from fusionlog.stages.estimate import run_estimate

    res = run_estimate(
        sensors,
        output,
        archs=list(archs),
        model_path=model,
        force=force,
        block=block_runs,
        command=_command_line(),
    )
    click.echo(f"{res.path}: {', '.join(res.architectures)} on {res.runs} runs")


@main.command()
@click.argument("sensors", type=PATH)
@click.argument("estimates", type=PATH)
@click.option("-o", "--output", type=PATH, required=True, help="Rerun recording (.rrd).")
@click.option("--summary", "summary_path", type=PATH, help="Also write summary.json here.")
@_force
@_block
def evaluate(sensors, estimates, output, summary_path, force, block_runs) -> None:
    """Evaluate ESTIMATES.mcap against the truth in SENSORS.mcap into a Rerun recording."""
    from fusionlog.report import format_table

    if _identity_log(sensors):
        from fusionlog.stages.identity import run_evaluate
    else:
        from fusionlog.stages.evaluate import run_evaluate

    res = run_evaluate(
        sensors, estimates, output, summary_path=summary_path, force=force, block=block_runs
    )
    click.echo(format_table(res.summary))
    click.echo(f"{res.recording}" + (f", {res.summary_path}" if res.summary_path else ""))


@main.command()
@click.argument("scenario", type=PATH)
@click.option(
    "--out-dir",
    type=click.Path(path_type=Path, file_okay=False),
    help="Output folder (default recordings/<scenario name>/).",
)
@_runs
@_steps
@_seed
@_arch
@_force
@_block
def run(scenario, out_dir, runs, steps, seed, archs, force, block_runs) -> None:
    """Simulate, estimate and evaluate SCENARIO.toml; print the results table."""
    from fusionlog.report import format_table

    sc = _scenario(scenario, runs, steps, seed)
    if _is_identity(sc):
        from fusionlog.stages.identity import (
            check_architectures,
            run_estimate,
            run_evaluate,
            run_simulate,
        )

        check_architectures(list(archs), "--arch")
    else:
        from fusionlog.stages.estimate import check_architectures, run_estimate
        from fusionlog.stages.evaluate import run_evaluate
        from fusionlog.stages.simulate import run_simulate

        check_architectures(list(archs), sc.system, "--arch")
    d = out_dir if out_dir is not None else Path("recordings") / sc.name
    outs = {k: d / k for k in ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")}
    if not force:
        for p in outs.values():
            if p.exists():
                raise FusionlogError(f"{p}: exists; use --force to overwrite")
    cmd = _command_line()
    # All four outputs are made in a staging folder beside them and moved into place together
    # at the end: a run that fails half-way leaves the previous outputs as they were, not a mix.
    d.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=d, prefix=".run-"))
    new = {k: staging / k for k in outs}
    try:
        t0 = time.perf_counter()
        run_simulate(sc, new["sensors.mcap"], block=block_runs, command=cmd)
        t1 = time.perf_counter()
        run_estimate(
            new["sensors.mcap"],
            new["estimates.mcap"],
            archs=list(archs) or list(sc.architectures),
            block=block_runs,
            command=cmd,
        )
        t2 = time.perf_counter()
        res = run_evaluate(
            new["sensors.mcap"],
            new["estimates.mcap"],
            new["evaluation.rrd"],
            summary_path=new["summary.json"],
            block=block_runs,
        )
        if not force:  # an output that appeared while we were running is not overwritten
            for p in outs.values():
                if p.exists():
                    raise FusionlogError(f"{p}: exists; use --force to overwrite")
        for k, p in outs.items():
            os.replace(new[k], p)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    t3 = time.perf_counter()
    click.echo(f"{sc.name}: M = {sc.runs} runs, K = {sc.steps}, seed {sc.seed}")
    click.echo(format_table(res.summary))
    click.echo(
        f"simulate {t1 - t0:.2f} s, estimate {t2 - t1:.2f} s, evaluate {t3 - t2:.2f} s -> {d}"
    )


@main.command()
@click.argument("recording", type=PATH)
@click.option("--json", "as_json", is_flag=True, help="Print summary.json instead of a table.")
def summary(recording, as_json) -> None:
    """Read EVALUATION.rrd back offline and print its results table."""
    from fusionlog.io.rrd import read_recording
    from fusionlog.report import format_table

    data = read_recording(recording)
    if as_json:
        click.echo(json.dumps(data["summary"], indent=2))
    else:
        s = data["summary"]
        click.echo(f"{s.get('scenario')}: M = {s.get('runs')} runs, K = {s.get('steps')}")
        click.echo(format_table(s))


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as e:
        raise FusionlogError(f"{path}: no such file") from e
    except (OSError, UnicodeDecodeError) as e:
        raise FusionlogError(f"{path}: cannot read ({e})") from e
    except json.JSONDecodeError as e:
        raise FusionlogError(f"{path}: not valid JSON (line {e.lineno}: {e.msg})") from e


@main.command()
@click.argument("actual", type=PATH)
@click.argument("golden", type=PATH)
@click.option("--rtol", type=float, default=1e-6, show_default=True, help="Relative tolerance.")
@click.option("--atol", type=float, default=1e-12, show_default=True, help="Absolute tolerance.")
def compare(actual, golden, rtol, atol) -> None:
    """Compare SUMMARY.json with GOLDEN.json; exit 1 if any metric moved beyond tolerance."""
    from fusionlog.report import compare_summaries

    docs = []
    for path in (actual, golden):
        doc = _load_json(path)
        if not isinstance(doc, dict) or not isinstance(doc.get("architectures"), dict):
            raise FusionlogError(f"{path}: not a fusionlog summary (no 'architectures' object)")
        docs.append(doc)
    diffs = compare_summaries(docs[0], docs[1], rtol=rtol, atol=atol)
    if diffs:
        click.echo(f"{actual} differs from {golden} (rtol={rtol:g}, atol={atol:g}):")
        for line in diffs:
            click.echo(f"  {line}")
        sys.exit(1)
    click.echo(f"{actual} matches {golden} (rtol={rtol:g}, atol={atol:g})")


@main.command()
@click.argument("file", type=PATH)
@click.option("--recover", is_flag=True, help="Read a damaged file as far as it goes.")
def inspect(file, recover) -> None:
    """Show what is in an MCAP file: scenario, topics, message counts, runs, steps."""
    from fusionlog.io.mcap import McapFile
    from fusionlog.io.mcap import recover as recover_file

    if recover:
        info = recover_file(file)
        click.echo(f"{file}: {'damaged: ' + str(info['error']) if info['error'] else 'intact'}")
        for t, c in sorted(info["topics"].items()):
            click.echo(f"  {t:32s} {c:8d} messages readable")
        click.echo(
            f"  complete runs: {info['complete_runs']}, "
            f"last complete step: {info['last_complete_step']}"
        )
        click.echo(f"  metadata: {', '.join(sorted(info['metadata'])) or 'none'}")
        return
    mf = McapFile(file)
    sc = mf.metadata.get("fusionlog.scenario", {})
    prov = mf.metadata.get("fusionlog.provenance", {})
    click.echo(f"{file}")
    if sc:
        click.echo(f"  scenario: {sc.get('name')} (seed {sc.get('seed')})")
    if prov:
        version = prov.get("fusionlog_version", "?")
        click.echo(f"  written by: {prov.get('command', '?')} (fusionlog {version})")
    ours = [t for t in mf.topics if mf.kind_of(t) is not None]
    if ours:
        click.echo(f"  runs: {mf.runs()}, instants: {mf.steps()} (k = 0..{mf.steps() - 1})")
    else:
        click.echo("  no fusionlog topics (no fusionlog.Block or fusionlog.EstimateBlock streams)")
    for t in sorted(mf.topics):
        kind = f"dim {mf.dim_of(t)}" if t in ours else "not a fusionlog stream"
        click.echo(f"  {t:32s} {mf.topics[t]:8d} messages  {mf.schema_of(t)}  {kind}")
    click.echo(f"  metadata: {', '.join(sorted(mf.metadata)) or 'none'}")


if __name__ == "__main__":
    main()
