"""The `fusionlog` command line: a thin click layer over `fusionlog.stages`.

Exit codes: 0 success, 1 a comparison found a regression, 2 bad usage or bad input (one line on
stderr naming the file and the problem; a traceback only with --debug), 130 interrupted.
"""

from __future__ import annotations

import os
import shlex
import signal
import sys
from pathlib import Path
from typing import Any

import click

from fusionlog import __version__, cli_identify
from fusionlog.cli_export import align_option, export
from fusionlog.cli_signals import Terminated, unwinding_on_signals
from fusionlog.errors import DamagedFile, FusionlogError, OutputExists
from fusionlog.memory import keep_freed_memory, leave_objects_at_exit, one_blas_thread

PATH = click.Path(path_type=Path, dir_okay=False)
#: An output file: whatever is at the path (a directory, a device) is refused by io/atomic.py
#: with the one line every other unsuitable target gets, not by click's usage message.
OUTPUT = click.Path(path_type=Path)


#: Exit codes (DESIGN.md): 0 success, 1 a regression found by `compare`, 2 bad usage, bad
#: input or a failed output (one line on stderr), 3 an internal error (a bug: one line; the
#: traceback with --debug), 128 + N killed by signal N (SIGINT 130, SIGHUP 129, SIGTERM 143;
#: SIGPIPE 141, quietly, when stdout's reader has gone).
EXIT_BAD_INPUT = 2
EXIT_INTERNAL = 3


def _hint(e: FusionlogError) -> str:
    """How to fix it, where that depends on the command line rather than on the library."""
    if isinstance(e, OutputExists):
        return "; use --force to overwrite"
    if isinstance(e, DamagedFile) and e.path is not None and e.recoverable:
        return f"; `fusionlog inspect --recover {e.path}` shows what is still readable"
    return ""


class _Group(click.Group):
    """One line and an exit code for every failure; SIGTERM/SIGHUP clean up like Ctrl-C (for
    this command only: a caller running it in process gets its own handlers back after)."""

    def invoke(self, ctx: click.Context) -> Any:
        debug = bool(ctx.params.get("debug"))
        keep_freed_memory()  # this process is fusionlog's: see fusionlog.memory
        one_blas_thread()
        leave_objects_at_exit()
        try:
            with unwinding_on_signals():
                return super().invoke(ctx)
        except (KeyboardInterrupt, Terminated, Exception) as e:
            passed_on = (click.exceptions.Exit, click.ClickException, click.Abort)
            if debug or (isinstance(e, passed_on) and not isinstance(e, click.UsageError)):
                raise
            line, code = _failure(e)
            if line:
                click.echo(line, err=True)
            ctx.exit(code)


def _failure(e: BaseException) -> tuple[str | None, int]:
    """The one line on stderr (None: none) and the exit code of a failed command."""
    if isinstance(e, FusionlogError):
        return f"fusionlog: error: {_one_line(str(e))}{_hint(e)}", EXIT_BAD_INPUT
    if isinstance(e, KeyboardInterrupt | Terminated):
        signum = e.signum if isinstance(e, Terminated) else signal.SIGINT
        return "fusionlog: interrupted; no partial output was left behind", 128 + int(signum)
    if isinstance(e, click.UsageError):  # one line too, not click's usage block
        sub = e.ctx.info_name if e.ctx is not None and e.ctx.parent is not None else None
        where = f"fusionlog {sub}" if sub else "fusionlog"
        line = f"fusionlog: error: {_one_line(e.format_message())} (see: {where} --help)"
        return line, EXIT_BAD_INPUT
    if isinstance(e, MemoryError):
        return "fusionlog: error: out of memory (use fewer runs per block or steps)", EXIT_BAD_INPUT
    if isinstance(e, BrokenPipeError):  # stdout closed early (`| head`): the reader's choice
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no flush error
        return None, 128 + signal.SIGPIPE
    if isinstance(e, OSError):  # a file the library did not name: still one line
        where = f"{e.filename}: " if e.filename else ""
        return f"fusionlog: error: {where}{e.strerror or e}", EXIT_BAD_INPUT
    return (
        f"fusionlog: internal error: {type(e).__name__}: {_one_line(str(e))} "
        "(please report it; --debug shows the traceback)",
        EXIT_INTERNAL,
    )


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _command_line() -> str:
    return " ".join(["fusionlog", *sys.argv[1:]])


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="fusionlog")
@click.option("--debug", is_flag=True, help="Show tracebacks instead of one-line errors.")
def main(debug: bool) -> None:
    """Simulate multi-sensor linear Gaussian systems to MCAP, replay them through fusion
    architectures, and evaluate the estimates into Rerun recordings."""


def _scenario(path: Path, runs, steps, seed, align=None, late=None, archs=()):
    """The scenario, of whichever kind the file is (decided once, by the loader); `align`:
    ``--align`` (overrides ``[evaluate] align``), `late`: ``--late`` ([estimate] late)."""
    from fusionlog.scenario import load_scenario
    from fusionlog.scenario.trajectory import with_align
    from fusionlog.stages.state_kind import scenario_with_late

    sc = with_align(load_scenario(path, runs=runs, steps=steps, seed=seed), align)
    return scenario_with_late(sc, late, archs)


def _warn_stale(targets: list[Path]) -> None:
    """Report temporary files a killed fusionlog left beside these outputs."""
    from fusionlog.io.atomic import stale_temporaries

    for t in targets:
        for p in stale_temporaries(t):
            click.echo(
                f"fusionlog: warning: {p} is a temporary file left by a killed fusionlog run "
                f"(its process is gone); remove it with: rm -- {shlex.quote(str(p))}",
                err=True,
            )


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
    # the registry's names, written out so that `--help` imports no numpy
    # (tests/test_docs.py::test_the_arch_help_names_every_registered_architecture)
    help="Architecture (repeatable): CKF, HKF, MSC, MSC-GMF, SKF[:sensor], CI, FBS, AVG, ICI, EI; "
    "BAYES, DS for identity scenarios.",
)
_filter = click.option("--filter", "filter_name", type=click.Choice(["EKF", "UKF"]),
                       help="Local filter of every architecture ([estimate] filter).")  # fmt: skip
_late = click.option("--late", type=click.Choice(["reprocess", "retrodict", "neglect"]),
                     help="Policy for late measurements ([estimate] late).")  # fmt: skip
_workers = click.option("--workers", type=click.IntRange(min=0), help="Compute the runs, in "
    "blocks, on a Dask LocalCluster of N worker processes (0: in this process, without Dask). "
    "Default: run, this process; sweep, from the size of the work (sweep --help).")  # fmt: skip
_scheduler = click.option("--scheduler", metavar="ADDRESS", help="Compute the runs, in blocks, "
    "on the running Dask cluster at ADDRESS (tcp://host:port or tls://host:port).")  # fmt: skip
_scheduler_timeout = click.option(
    "--scheduler-timeout",
    type=float,
    default=10.0,
    show_default=True,
    metavar="SECONDS",
    help="With --scheduler: how long to wait for the scheduler to answer, and for a worker "
    "when it has none (also while the runs are computed).",
)


def _one_executor(workers: int | None, scheduler: str | None) -> None:
    if workers is not None and scheduler is not None:
        raise click.UsageError("--workers and --scheduler: give one of them, not both")


def _out_dir(default: str):
    """The --out-dir option of a command that writes several outputs into one folder."""
    return click.option(
        "--out-dir",
        type=click.Path(path_type=Path, file_okay=False),
        help=f"Output folder (default {default}).",
    )


@main.command()
@click.argument("scenario", type=PATH)
@click.option("-o", "--output", type=OUTPUT, required=True, help="Sensors MCAP file to write.")
@_runs
@_steps
@_seed
@_force
@_block
def simulate(scenario, output, runs, steps, seed, force, block_runs) -> None:
    """Simulate SCENARIO.toml: truth and sensor streams into an MCAP file."""
    from fusionlog.stages.simulate import run_simulate

    sc = _scenario(scenario, runs, steps, seed)
    res = run_simulate(sc, output, force=force, block=block_runs, command=_command_line())
    click.echo(f"{res.path}: {res.runs} runs x {res.steps + 1} steps, {res.messages} messages")


@main.command("import")
@click.argument("replay", type=PATH)
@click.option("-o", "--output", type=OUTPUT, required=True, help="Sensors MCAP file to write.")
@_force
def import_(replay, output, force) -> None:
    """Import a replay file's recorded data (MCAP of any encoding, CSV) as a sensors file."""
    from fusionlog.stages.import_data import run_import

    res = run_import(_scenario(replay, None, None, None), output, force=force,
                     command=_command_line())  # fmt: skip
    for note in res.notes:
        click.echo(f"note: {note}")
    click.echo(f"{res.path}: 1 run x {res.instants} instants, {res.messages} messages")


@main.command()
@click.argument("sensors", type=PATH)
@click.option("-o", "--output", type=OUTPUT, required=True, help="Estimates MCAP file to write.")
@_arch
@click.option("--model", type=PATH, help="Filter model TOML replacing the recorded scenario's.")
@_filter
@_late
@_force
@_block
def estimate(sensors, output, archs, model, filter_name, late, force, block_runs) -> None:
    """Replay SENSORS.mcap through fusion architectures into an estimates MCAP file."""
    from fusionlog.stages.estimate import run_estimate

    res = run_estimate(
        sensors,
        output,
        archs=list(archs),
        model_path=model,
        filter_name=filter_name,
        force=force,
        block=block_runs,
        command=_command_line(),
        late=late,
    )
    click.echo(f"{res.path}: {', '.join(res.architectures)} on {res.runs} runs")


@main.command()
@click.argument("sensors", type=PATH)
@click.argument("estimates", type=PATH)
@click.option("-o", "--output", type=OUTPUT, required=True, help="Rerun recording (.rrd).")
@click.option("--summary", "summary_path", type=OUTPUT, help="Also write summary.json here.")
@align_option
@_force
@_block
def evaluate(sensors, estimates, output, summary_path, align, force, block_runs) -> None:
    """Evaluate ESTIMATES.mcap against the truth in SENSORS.mcap into a Rerun recording."""
    from fusionlog.report import format_table
    from fusionlog.stages.evaluate import run_evaluate

    res = run_evaluate(sensors, estimates, output, summary_path=summary_path, force=force,
                       block=block_runs, align=align)  # fmt: skip
    click.echo(format_table(res.summary, res.sensors))
    click.echo(f"{res.recording}" + (f", {res.summary_path}" if res.summary_path else ""))


@main.command()
@click.argument("scenario", type=PATH)
@_out_dir("recordings/<scenario name>/")
@_runs
@_steps
@_seed
@_arch
@_filter
@_late
@align_option
@_force
@_block
@_workers
@_scheduler
@_scheduler_timeout
def run(scenario, out_dir, runs, steps, seed, archs, filter_name, late, align, force, block_runs,
        workers, scheduler, scheduler_timeout) -> None:  # fmt: skip
    """Simulate, estimate and evaluate SCENARIO.toml; print the results table.

    With --workers or --scheduler the runs are computed on Dask in blocks whose metric sums
    are merged here: only evaluation.rrd and summary.json are written (the MCAP logs would
    carry every estimate back); the sample runs are computed here."""
    _one_executor(workers, scheduler)
    if workers is not None or scheduler is not None:
        _run_distributed(scenario, out_dir, runs, steps, seed, archs, force, block_runs, workers,
                         scheduler, scheduler_timeout, filter_name, align, late)  # fmt: skip
        return
    from fusionlog.report import format_table, headline
    from fusionlog.stages.kinds import kind_of
    from fusionlog.stages.run import RUN_OUTPUTS, run_pipeline

    sc = _scenario(scenario, runs, steps, seed, align, late, archs)
    archs = kind_of(sc.kind).check_architectures(list(archs), sc.system, "--arch")
    d = out_dir if out_dir is not None else Path("recordings") / sc.name
    _warn_stale([d / k for k in RUN_OUTPUTS])
    res = run_pipeline(
        sc,
        d,
        archs=archs,
        filter_name=filter_name,
        force=force,
        block=block_runs,
        command=_command_line(),
        inputs=[scenario],
    )
    sc = res.scenario
    for note in res.notes:
        click.echo(f"note: {note}")
    click.echo(headline(sc))
    click.echo(format_table(res.summary, [s.name for s in sc.system.sensors]))
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in res.seconds.items())
    click.echo(f"{stages} -> {d}")


def _run_distributed(scenario, out_dir, runs, steps, seed, archs, force, block, workers,
                     scheduler, timeout, filter_name, align, late=None):  # fmt: skip
    """`run --workers/--scheduler`: evaluation.rrd and summary.json from metric sums."""
    from fusionlog.report import format_table, headline
    from fusionlog.stages.distributed_run import DISTRIBUTED_OUTPUTS, run_distributed

    sc = _scenario(scenario, runs, steps, seed, align, late, archs)
    d = out_dir if out_dir is not None else Path("recordings") / sc.name
    _warn_stale([d / name for name in DISTRIBUTED_OUTPUTS])
    res = run_distributed(
        sc,
        d,
        archs=list(archs),
        workers=workers,
        scheduler=scheduler,
        scheduler_timeout=timeout,
        force=force,
        block=block,
        command=_command_line(),
        filter_name=filter_name,
    )
    click.echo(headline(sc))
    click.echo(format_table(res.summary, [s.name for s in sc.system.sensors]))
    click.echo(f"{res.executor}: {res.seconds:.2f} s -> {d} (evaluation.rrd, summary.json)")


@main.command()
@click.argument("scenario", type=PATH)
@click.option(
    "--vary",
    multiple=True,
    required=True,
    metavar="KEY=VALUES",
    help="A dotted key of the scenario (scenario.dt, model.n0, sensors.<name>.R, "
    "sensors.<name>.dropout, correlations.0.cov, ...) and its values: a comma list "
    "(0.5,1,2) or start:stop:num[:log]. Repeat for a grid (the product).",
)
@_runs
@_out_dir("recordings/<scenario name>_sweep/")
@_arch
@_workers
@_scheduler
@_scheduler_timeout
@click.option(
    "--exact-only",
    is_flag=True,
    help="Only the exact analysis, no Monte Carlo (in this process unless --workers or "
    "--scheduler is given).",
)
@_force
@_block
def sweep(
    scenario, vary, runs, out_dir, archs, workers, scheduler, scheduler_timeout, exact_only,
    force, block_runs,
):  # fmt: skip
    """Evaluate SCENARIO.toml over a grid of parameter values, on Dask: writes sweep.parquet,
    sweep.rrd and summary.json (no MCAP logs: workers return metric sums).

    Without --workers or --scheduler: a LocalCluster of one worker per CPU when the work is
    estimated above 2 s in one process (runs x instants x architectures, dropouts 40x),
    else this process (so too --exact-only, and one CPU): a cluster's start costs more."""
    from fusionlog.report import format_table
    from fusionlog.stages.sweep import run_sweep

    _one_executor(workers, scheduler)
    res = run_sweep(
        scenario,
        list(vary),
        runs=runs,
        out_dir=out_dir,
        archs=list(archs),
        workers=workers,
        scheduler=scheduler,
        scheduler_timeout=scheduler_timeout,
        exact_only=exact_only,
        force=force,
        block=block_runs,
        warn_stale=_warn_stale,
    )
    s = res.summary
    what = "exact analysis only" if s["exact_only"] else f"M = {s['runs']} runs per point"
    click.echo(f"{s['scenario']} sweep: {len(s['points'])} grid points, {what}")
    click.echo(format_table(s))
    t = res.timings
    click.echo(
        f"{res.executor}: {res.seconds:.2f} s (start {t['start']:.2f} s, {res.tasks} tasks "
        f"{t['tasks']:.2f} s, outputs {t['outputs']:.2f} s, stop {t['stop']:.2f} s) "
        f"-> {res.out_dir} (sweep.parquet, sweep.rrd, summary.json)"
    )


@main.command()
@click.argument("recording", type=PATH)
@click.option("--json", "as_json", is_flag=True, help="Print summary.json instead of a table.")
def summary(recording, as_json) -> None:
    """Read EVALUATION.rrd back offline and print its results table."""
    from fusionlog.io.rrd import read_recording
    from fusionlog.jsonout import dumps
    from fusionlog.report import recording_report

    rec = read_recording(recording, series=False)  # the table needs no series
    s = rec["summary"]
    if not isinstance(s, dict):
        kind = type(s).__name__ if s is not None else "null"
        raise FusionlogError(f"{recording}: the summary property is not a JSON object ({kind})")
    if as_json:
        click.echo(dumps(s, indent=2))  # strict JSON, also from a recording made before it was
        return
    try:
        click.echo(recording_report(s, rec["properties"]))
    except ValueError as e:
        raise FusionlogError(f"{recording}: the summary property is not a summary ({e})") from None


def _tolerance(name: str, default: float, text: str):
    """--rtol / --atol: a finite number >= 0 (else a usage error, exit 2)."""

    def check(ctx: click.Context, param: click.Parameter, value: float) -> float:
        from fusionlog.compare import check_tolerance

        try:
            return check_tolerance(value, name)
        except ValueError:
            raise click.BadParameter(f"must be a finite number >= 0, got {value:g}") from None

    return click.option(
        name, type=float, default=default, show_default=True, callback=check, help=text
    )


@main.command()
@click.argument("actual", type=PATH)
@click.argument("golden", type=PATH)
@_tolerance("--rtol", 1e-6, "Relative tolerance.")
@_tolerance("--atol", 1e-12, "Absolute tolerance.")
def compare(actual, golden, rtol, atol) -> None:
    """Compare SUMMARY.json with GOLDEN.json; exit 1 if any metric moved beyond tolerance.

    A file that is not a well-formed summary (not strict JSON, a metric that is not a number)
    is bad input (exit 2), not a regression. A sweep's summary.json compares point by point."""
    from fusionlog.compare import check_summary, compare_summaries, load_json

    docs = []
    for path in (actual, golden):
        doc = load_json(path)
        sweep = isinstance(doc, dict) and doc.get("kind") == "sweep"  # architectures per point
        if not isinstance(doc, dict) or not (sweep or isinstance(doc.get("architectures"), dict)):
            raise FusionlogError(f"{path}: not a fusionlog summary (no 'architectures' object)")
        try:
            docs.append(check_summary(doc, strict=True))
        except ValueError as e:
            raise FusionlogError(f"{path}: {e}") from None
    diffs = compare_summaries(docs[0], docs[1], rtol=rtol, atol=atol)
    if diffs:
        click.echo(f"{actual} differs from {golden} (rtol={rtol:g}, atol={atol:g}):")
        for line in diffs:
            click.echo(f"  {line}")
        sys.exit(1)
    click.echo(f"{actual} matches {golden} (rtol={rtol:g}, atol={atol:g})")


@main.command()
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--recover", is_flag=True, help="Read a damaged file as far as it goes.")
def inspect(file, recover) -> None:
    """Show a log (MCAP, ROS 1 .bag, ROS 2 bag): topics, counts, rates, a foreign topic's fields."""
    from fusionlog.stages.inspect import describe, describe_damaged

    _warn_stale([file])
    for line in describe_damaged(file) if recover else describe(file):
        click.echo(line)


main.add_command(cli_identify.identify)
main.add_command(export)

if __name__ == "__main__":
    main()
