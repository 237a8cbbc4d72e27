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
   metrics against the swept parameter, :mod:`fusionlog.io.rrd.sweep`) and ``summary.json``
   (the same numbers, per point as ``fusionlog run`` reports them, and the lowest MSE of each
   architecture over the grid).

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

__all__ = ["OUTPUTS", "SweepResult", "run_sweep", "sweep_table"]

#: The sweep's outputs in its folder (DESIGN.md, CLI).
OUTPUTS = ("sweep.parquet", "sweep.rrd", "summary.json")
#: The parquet columns after the varied keys (DESIGN.md, "sweep.parquet").
METRIC_COLUMNS = (
    "mse",
    "anees",
    "dm",
    "nees_fraction_inside",
    "expected_mse",
    "expected_anees",
)


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
        where = "--arch" if archs else f"{p.scenario.path} [point {p.index}: {p.label}]"
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
    with Outputs(targets, force=force, inputs=[Path(scenario_path)]) as outs, ex:
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
        # the writers' imports (rerun, pyarrow: a second or more) while the workers compute
        threading.Thread(target=_import_writers, daemon=True).start()
        with contextlib.closing(ex.map(tasks, "sweep")) as results:
            for i, result in zip(owner, results, strict=True):
                if isinstance(result, BlockSums):
                    fold(sums[i], result, conditional[i])
                    busy += result.seconds
                else:
                    expected[i] = result
        ex.release()
        t.append(time.perf_counter())
        for i, job in enumerate(jobs):
            if job.conditional:
                expected[i] = _conditional_expected(job, sums[i], conditional[i])
        summary = _summary(varies, points, jobs, expected, sums, exact_only)
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
#: process runs in this process: a LocalCluster's start (worker processes importing numpy,
#: Dask and fusionlog, ~1-2 s of CPU each on two cores) costs about what a second core
#: would give back on work of a few seconds (benchmarks/README.md, "Sweeps on Dask").
LOCAL_BELOW_SECONDS = 5.0


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
    few seconds (`LOCAL_BELOW_SECONDS`), or one CPU (a one-worker cluster only adds its
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
        out[a] = expected_overall(ce) | {"conditional": True} if ok else None
    return out


def _import_writers() -> None:
    """Import what writing the outputs needs (Python's import lock makes the writer wait for
    an import under way here rather than repeat it)."""
    import pyarrow.parquet  # noqa: F401

    import fusionlog.io.rrd.sweep  # noqa: F401


def _point_summary(
    job: Job, expected: dict[str, Any], sums: dict[str, Any], exact_only: bool
) -> dict[str, Any]:
    """A point's architectures as ``fusionlog run``'s summary.json has them (Monte Carlo
    metrics from the merged sums, `expected` from the exact analysis, which has DM too)."""
    out = {}
    for a in job.archs:
        ex = expected.get(a)
        exp = dict(ex) if ex is not None else {"mse": None, "anees": None, "dm": None}
        if exact_only:
            out[a] = {"expected": exp}
            continue
        entry = sums[a].finalize(job.scenario.confidence).summary()
        entry["expected"] = exp
        out[a] = entry
    return out


def _bound(scenario: Any) -> dict[str, Any]:
    """A nonlinear point's PCRB ({"pcrb": ...}, `nonlinear.scenario_bound`), else nothing."""
    from .nonlinear import scenario_bound

    bound = scenario_bound(scenario)
    return {} if bound is None else {"pcrb": bound}


def _lowest(points: list[dict[str, Any]]) -> dict[str, Any]:
    """Each architecture's grid point of lowest MSE: the exact value where every point has
    one, else the Monte Carlo one."""
    best: dict[str, Any] = {}
    archs = dict.fromkeys(a for p in points for a in p["architectures"])
    for a in archs:
        have = [p for p in points if a in p["architectures"]]
        exact = all(p["architectures"][a]["expected"]["mse"] is not None for p in have)

        def value(p: dict[str, Any], exact: bool = exact, a: str = a) -> float:
            e = p["architectures"][a]
            v = e["expected"]["mse"] if exact else e.get("mse")
            return float("inf") if v is None or v != v else float(v)

        p = min(have, key=value)
        if value(p) == float("inf"):
            continue
        e = p["architectures"][a]
        best[a] = {
            "by": "expected" if exact else "monte-carlo",
            "point": p["index"],
            "values": p["values"],
            "expected_mse": e["expected"]["mse"],
            "mse": e.get("mse"),
        }
    return best


def _summary(
    varies: Sequence[Vary],
    points: Sequence[GridPoint],
    jobs: Sequence[Job],
    expected: Sequence[dict[str, Any]],
    sums: Sequence[dict[str, Any]],
    exact_only: bool,
) -> dict[str, Any]:
    """summary.json of a sweep (README, "Parameter sweeps"): the grid, every point as
    ``fusionlog run`` would summarise it, and each architecture's lowest MSE."""
    first = points[0].scenario
    per_point = [
        {
            "index": p.index,
            "values": p.values,
            "seed": p.scenario.seed,
            "runs": 0 if exact_only else p.scenario.runs,
            "steps": p.scenario.instants - 1,
            "architectures": _point_summary(job, e, s, exact_only),
        }
        | _bound(p.scenario)
        for p, job, e, s in zip(points, jobs, expected, sums, strict=True)
    ]
    return {
        "kind": "sweep",
        "scenario": first.name,
        "seed": points[0].file_seed,
        "runs": 0 if exact_only else first.runs,
        "steps": first.instants - 1,
        "state_names": list(first.state_names),
        "confidence": first.confidence,
        "exact_only": exact_only,
        "grid": [
            {"key": v.key, "values": list(v.values), "log": v.log, "numeric": v.numeric}
            for v in varies
        ],
        "points": per_point,
        "lowest_mse": _lowest(per_point),
    }


def sweep_table(summary: dict[str, Any]) -> list[dict[str, Any]]:
    """The rows of sweep.parquet (DESIGN.md): the varied keys' values, the architecture, the
    runs, the Monte Carlo metrics and the expected ones (None where there are none)."""
    keys = [g["key"] for g in summary["grid"]]
    rows = []
    for p in summary["points"]:
        for a, e in p["architectures"].items():
            row: dict[str, Any] = {k: p["values"][k] for k in keys}
            row["architecture"] = a
            row["runs"] = p["runs"]
            for m in ("mse", "anees", "dm", "nees_fraction_inside"):
                row[m] = e.get(m)
            row["expected_mse"] = e["expected"]["mse"]
            row["expected_anees"] = e["expected"]["anees"]
            rows.append(row)
    return rows


def _parquet(rows: list[dict[str, Any]], varies: Sequence[Vary], meta: dict[str, str]) -> bytes:
    """sweep.parquet as bytes: a key column of numbers (int64 when every value is an integer),
    booleans or strings as the values are, else the values as written (TOML text)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns: dict[str, Any] = {}
    for v in varies:
        vals = [r[v.key] for r in rows]
        if all(isinstance(x, bool) for x in v.values):
            columns[v.key] = pa.array(vals, pa.bool_())
        elif v.numeric and all(isinstance(x, int) for x in v.values):
            columns[v.key] = pa.array(vals, pa.int64())
        elif v.numeric:
            columns[v.key] = pa.array([float(x) for x in vals], pa.float64())
        elif all(isinstance(x, str) for x in v.values):
            columns[v.key] = pa.array(vals, pa.string())
        else:
            text = dict(zip(map(repr, v.values), v.texts, strict=True))
            columns[v.key] = pa.array([text[repr(x)] for x in vals], pa.string())
    columns["architecture"] = pa.array([r["architecture"] for r in rows], pa.string())
    columns["runs"] = pa.array([r["runs"] for r in rows], pa.int64())
    for m in METRIC_COLUMNS:
        # NaN (no defined step) and None (not computed) are both null: no value
        vals = [r[m] if r[m] is not None and r[m] == r[m] else None for r in rows]
        columns[m] = pa.array(vals, pa.float64())
    table = pa.table(columns).replace_schema_metadata(meta)
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


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
    from fusionlog.io.rrd.sweep import write_sweep_recording

    parquet_path, rrd_path, json_path = targets
    text = dumps(summary, indent=2) + "\n"
    meta = {
        "fusionlog_version": __version__,
        "scenario": summary["scenario"],
        "seed": str(summary["seed"]),
        "grid": dumps(summary["grid"]),
    }
    data = _parquet(rows, varies, meta)
    write_all(outs.open(parquet_path), data)
    outs.open(json_path).write(text.encode())
    write_sweep_recording(outs.open(rrd_path), summary, properties={"ran on": ran_on})
