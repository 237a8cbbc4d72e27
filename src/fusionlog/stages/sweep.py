"""``fusionlog sweep``: a scenario evaluated over a grid of parameter values, on Dask.

1. The grid (:mod:`.grid`): every point a scenario validated by the normal loader, all of them
   before anything runs; the outputs are checked (exist without --force, not an input) too.
2. The tasks (:mod:`.montecarlo`): per grid point one exact analysis (covariance analysis of
   every architecture: the expected MSE, ANEES, DM) and, unless ``exact_only``, its Monte
   Carlo runs in blocks (where runs differ in their measurement patterns, dropouts, the blocks
   also sum each run's exact statistics: the expected values conditional on the patterns);
   each point has its own seed (:func:`.grid.point_seed`), each chunk of runs its own random
   stream, and the blocks' metric sums come back in task order (:mod:`.distributed`), so the
   table is the same for any number of workers or scheduler.
3. The outputs, committed together through :class:`fusionlog.io.atomic.Outputs`:
   ``sweep.parquet`` (DESIGN.md: one row per grid point and architecture), ``sweep.rrd`` (the
   metrics against the swept parameter, :mod:`fusionlog.io.rrd.sweep_recording`) and
   ``summary.json`` (the same numbers, per point as ``fusionlog run`` reports them, and the
   lowest MSE of each architecture over the grid).

No sensor or estimate log is written: workers send back metric sums, never estimates.
"""

from __future__ import annotations

import contextlib
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog import __version__
from fusionlog.errors import FusionlogError
from fusionlog.io.atomic import Outputs
from fusionlog.jsonout import dumps

from .distributed import CONNECT_TIMEOUT, default_workers, executor
from .grid import GridPoint, Vary, grid_points, parse_vary
from .kinds import kind_of
from .montecarlo import (
    BlockSums,
    Job,
    block_sums,
    blocks,
    exact_mask,
    expected_overall,
    fold,
    point_expected,
)
from .sweep_outputs import parquet_bytes, sweep_summary, sweep_table

__all__ = ["OUTPUTS", "SweepResult", "run_sweep", "sweep_table"]

#: The sweep's outputs in its folder (DESIGN.md, CLI).
OUTPUTS = ("sweep.parquet", "sweep.rrd", "summary.json")


@dataclass
class SweepResult:
    out_dir: Path
    summary: dict[str, Any]
    rows: list[dict[str, Any]]
    executor: str  # what ran the tasks
    seconds: float
    #: wall seconds of the phases: "start" (the cluster), "tasks", "outputs", "stop"; and
    #: "busy", the seconds the workers spent in block tasks (for the per-task overhead)
    timings: dict[str, float] = field(default_factory=dict)
    tasks: int = 0


def _archs(points: Sequence[GridPoint], archs: Sequence[str]) -> list[tuple[str, ...]]:
    """Each point's architectures: --arch, checked against every point's sensors, or the
    point's own [estimate] list."""
    kind = kind_of("state")
    out = []
    for p in points:
        chosen = archs or p.scenario.architectures
        where = "--arch" if archs else p.where
        out.append(tuple(kind.check_architectures(list(chosen), p.scenario.system, where)))
    return out


def run_sweep(
    scenario_path: str | Path,
    vary: Sequence[str],
    *,
    runs: int | None = None,
    out_dir: Path | None = None,
    archs: Sequence[str] = (),
    workers: int | None = None,
    scheduler: str | None = None,
    scheduler_timeout: float = CONNECT_TIMEOUT,
    exact_only: bool = False,
    force: bool = False,
    block: int | None = None,
    warn_stale: Callable[[list[Path]], None] | None = None,
) -> SweepResult:
    """Evaluate the scenario at every point of the grid `vary` (``KEY=VALUES`` strings) and
    write sweep.parquet, sweep.rrd and summary.json into `out_dir` (default
    ``recordings/<name>_sweep``), all three or none.

    `workers` N starts a LocalCluster of N processes (0: everything in this process), a
    `scheduler` address uses a running cluster; neither: one process per CPU, except with
    `exact_only` (milliseconds per point and architecture) and for work estimated at a few
    seconds in one process (`small_work`), which run here: not worth a cluster. `block` sets
    the runs per task (the default keeps a task near a million run-steps). `warn_stale` is
    shown the outputs first (the CLI reports temporary files a killed run left beside
    them)."""
    varies = [parse_vary(s) for s in vary]
    points = grid_points(scenario_path, varies, runs=runs)
    first = points[0].scenario
    if first.replay is not None:  # a sweep simulates runs at each point: a log has one
        raise FusionlogError(
            f"{scenario_path}: a replay is one recorded run, not a scenario to simulate at "
            "grid points: sweep a scenario file, or run the replay once per model"
        )
    point_archs = _archs(points, archs)
    d = Path(out_dir) if out_dir is not None else Path("recordings") / f"{first.name}_sweep"
    targets = [d / name for name in OUTPUTS]
    if warn_stale is not None:
        warn_stale(targets)
    small = exact_only or small_work(points, point_archs)
    ex = executor(workers, scheduler, local_default=small, timeout=scheduler_timeout)
    t = [time.perf_counter()]
    busy = 0.0
    # The outputs are checked before the cluster starts: a sweep that cannot write its results
    # is refused at once, not after its runs.
    with (
        Outputs(targets, force=force, inputs=[Path(scenario_path)]) as outs,
        ex,
        contextlib.ExitStack() as stack,
    ):
        t.append(time.perf_counter())
        token = uuid.uuid4().hex
        # points whose runs differ in their patterns (dropouts) have no exact analysis of
        # their own: their blocks sum each run's, given its pattern (the conditional value)
        jobs = [
            Job(
                p.scenario,
                a,
                f"{token}:{p.index}",
                not exact_only and not exact_mask(p.scenario)[0],
                p.where,
            )
            for p, a in zip(points, point_archs, strict=True)
        ]
        tasks: list = []
        owner: list[int] = []  # the point of each task
        for i, job in enumerate(jobs):
            tasks.append((point_expected, (job,)))
            owner.append(i)
            if not exact_only:
                for off, n in blocks(job.scenario, block):
                    tasks.append((block_sums, (job, off, n)))
                    owner.append(i)
        expected: list[dict[str, Any]] = [{} for _ in points]
        sums: list[dict[str, Any]] = [{} for _ in points]
        conditional: list[dict[str, Any]] = [{} for _ in points]
        trajectory: list[dict[str, Any]] = [{} for _ in points]  # APE/RPE sums
        # the writers' imports (rerun, pyarrow, scipy.special: a second or more) while the
        # workers compute (forked ones are up by now: `worker_signals.FORK`)
        importer = threading.Thread(target=_import_writers, daemon=True)
        importer.start()
        # a failed or interrupted sweep waits for it: a thread still importing C extensions
        # while the interpreter shuts down may crash it
        stack.callback(importer.join, 30)
        with contextlib.closing(ex.map(tasks, "sweep")) as results:
            for i, result in zip(owner, results, strict=True):
                if isinstance(result, BlockSums):
                    fold(sums[i], result, conditional[i], trajectory[i])
                    busy += result.seconds
                else:
                    expected[i] = result
        ex.release()
        t.append(time.perf_counter())
        for i, job in enumerate(jobs):
            if job.conditional:
                expected[i] = _conditional_expected(job, sums[i], conditional[i])
        summary = sweep_summary(varies, points, jobs, expected, sums, exact_only, trajectory)
        rows = sweep_table(summary)
        _write(outs, targets, summary, rows, varies, ex.description)
        outs.commit()
        t.append(time.perf_counter())
    t.append(time.perf_counter())
    phases = dict(zip(("start", "tasks", "outputs", "stop"), np.diff(t).tolist(), strict=True))
    return SweepResult(
        d, summary, rows, ex.description, t[-1] - t[0], phases | {"busy": busy}, len(tasks)
    )


#: CPU seconds of the Monte Carlo per run, instant and architecture in one process, simulation
#: and metric sums included: the paper's example (shared gains) ~5e-8 s; where the runs'
#: measurement patterns differ (dropouts: per-run plans and each run's exact statistics) or
#: a nonlinear model gives every run its own covariances, about 40 times that (measured
#: with `benchmarks/bench_sweep.py` and in-process sweeps).
SECONDS_PER_RUN_STEP = 5e-8
PER_RUN_FACTOR = 40
#: Without --workers, a sweep whose Monte Carlo is estimated below this many seconds in one
#: process runs in this process: a LocalCluster (Dask imported here and its scheduler,
#: ~0.3 s before the first task; workers forked in hundredths of a second) costs about what
#: a second core gives back on a second of work. Measured on the paper's sweep (4 points,
#: 7 architectures; benchmarks/README.md, issue 23): 2e4 runs per point, estimated 0.6 s
#: (about 1 s of tasks), take 1.36-1.45 s here and 1.46-1.53 s on two workers; 2e5 runs,
#: estimated 5.9 s, 6.3-6.9 s here and 4.2-4.4 s on two workers. Break-even near 1.3 s.
LOCAL_BELOW_SECONDS = 2.0


def estimated_seconds(points: Sequence[GridPoint], point_archs: Sequence[tuple[str, ...]]) -> float:
    """The Monte Carlo's CPU seconds in one process, from the size of the work alone."""
    total = 0.0
    for p, archs in zip(points, point_archs, strict=True):
        sc = p.scenario
        # each run with its own covariances: dropouts, or EKF/UKF local filters
        per_run = not sc.system.linear or any(s.timing.dropout > 0 for s in sc.system.sensors)
        factor = PER_RUN_FACTOR if per_run else 1
        total += sc.runs * sc.instants * len(archs) * factor * SECONDS_PER_RUN_STEP
    return total


def small_work(points: Sequence[GridPoint], point_archs: Sequence[tuple[str, ...]]) -> bool:
    """Whether the default (no --workers, no --scheduler) is this process: estimated work of a
    couple of seconds (`LOCAL_BELOW_SECONDS`), or one CPU (a one-worker cluster only adds its
    start to the same work)."""
    return default_workers() < 2 or estimated_seconds(points, point_archs) < LOCAL_BELOW_SECONDS


def _conditional_expected(
    job: Job, sums: dict[str, Any], conditional: dict[str, Any]
) -> dict[str, Any]:
    """A dropout point's expected values: the run averages of each run's exact statistics,
    marked conditional (DESIGN.md, summary.json), where they cover every run of the Monte
    Carlo metrics (else none)."""
    out: dict[str, Any] = {}
    for a in job.archs:
        ce = conditional.get(a)
        ok = ce is not None and a in sums and ce.runs == sums[a].runs
        if ok:
            from fusionlog.core.bound import bound_summary

            out[a] = expected_overall(ce) | {"conditional": True, "bound": bound_summary(ce.bound)}
        else:
            out[a] = None
    return out


def _import_writers() -> None:
    """Import what writing the outputs needs (Python's import lock makes the writer wait for
    an import under way here rather than repeat it)."""
    import pyarrow.parquet  # noqa: F401
    import scipy.special  # noqa: F401  (the NEES bounds of the summary: core.metrics)

    import fusionlog.io.rrd.sweep_recording  # noqa: F401


def _write(
    outs: Outputs,
    targets: list[Path],
    summary: dict[str, Any],
    rows: list[dict[str, Any]],
    varies: Sequence[Vary],
    ran_on: str,
) -> None:
    """The three outputs into their (uncommitted) temporary files; the recording last, after
    the two that can fail on the data (strict JSON, the parquet schema)."""
    from fusionlog.io.rrd.stream import write_all
    from fusionlog.io.rrd.sweep_recording import write_sweep_recording

    parquet_path, rrd_path, json_path = targets
    text = dumps(summary, indent=2) + "\n"
    meta = {
        "fusionlog_version": __version__,
        "scenario": summary["scenario"],
        "seed": str(summary["seed"]),
        "grid": dumps(summary["grid"]),
    }
    data = parquet_bytes(rows, varies, meta)
    write_all(outs.open(parquet_path), data)
    outs.open(json_path).write(text.encode())
    write_sweep_recording(outs.open(rrd_path), summary, properties={"ran on": ran_on})
