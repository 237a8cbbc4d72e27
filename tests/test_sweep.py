"""`fusionlog sweep` and `fusionlog run --workers/--scheduler` (issue 15): the grid, the Dask
execution, the outputs.

The table must be identical whatever runs it (this process, a LocalCluster of 1 or 2 workers,
a real `dask scheduler` with two `dask worker` processes on 127.0.0.1), the exact column must
be the covariance analysis of each point, a sweep point's Monte Carlo must be `fusionlog run`'s
with the point's seed, and every failure is one line. Sizes are small (a few thousand runs,
three architectures) so the file stays well under a minute on two cores: most of its time is
starting the three clusters.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import psutil
import pyarrow.parquet as pq
import pytest
from cli_helpers import cli, ok, one_line_error
from dask_cluster import ENV, free_port, loopback_cluster

from fusionlog.core.architectures import build_plan
from fusionlog.core.exact import analyse
from fusionlog.core.metrics import MetricsAccumulator
from fusionlog.errors import FusionlogError
from fusionlog.io.rrd import entity_path
from fusionlog.scenario import load_scenario, scenario_from_text, scenario_with
from fusionlog.stages.grid import grid_points, parse_vary, point_seed
from fusionlog.stages.montecarlo import Job, block_estimates, block_sums, blocks, fold

ROOT = Path(__file__).resolve().parents[1]
AJGL = ROOT / "pipeline" / "ajgl2009.toml"
BIN = Path(sys.executable).parent
ARCHS = ["--arch", "CKF", "--arch", "MSC", "--arch", "SKF"]
# two grid points, three blocks of runs each (834, 834 and 832 runs)
SMALL = ["--vary", "scenario.dt=0.5,2", "--runs", "2500", "--block-runs", "1000", *ARCHS]
COLUMNS = [
    "scenario.dt",
    "architecture",
    "runs",
    "mse",
    "anees",
    "dm",
    "nees_fraction_inside",
    "expected_mse",
    "expected_anees",
    "bound_worst",
]


def table(d: Path):
    return pq.read_table(d / "sweep.parquet")


# ------------------------------------------------------------------------------------- grid


@pytest.mark.parametrize(
    "spec, values, log",
    [
        ("scenario.dt=0.5,1,2", (0.5, 1, 2), False),
        ("scenario.dt=0.1:0.5:5", (0.1, 0.2, 0.3, 0.4, 0.5), False),
        ("scenario.dt=0.01:100:5:log", (0.01, 0.1, 1.0, 10.0, 100.0), True),
        ("scenario.steps=10:30:3", (10, 20, 30), False),
        ("scenario.dt=3:3:1", (3,), False),
        ("sensors.s1.R=[[1.0]],[[2.5]]", ([[1.0]], [[2.5]]), False),
        ("model.kind=continuous", ("continuous",), False),
        ('model.kind="constant-velocity"', ("constant-velocity",), False),
    ],
)
def test_values_lists_and_ranges(spec: str, values: tuple, log: bool) -> None:
    v = parse_vary(spec)
    assert v.values == values and v.log == log
    for got, want in zip(v.values, values, strict=True):
        assert type(got) is type(want)


@pytest.mark.parametrize(
    "spec, fragment",
    [
        ("scenario.dt", "expected KEY=VALUES"),
        ("=1,2", "expected KEY=VALUES"),
        ("scenario..dt=1", "empty part"),
        ("scenario.dt=", "an empty value"),
        ("scenario.dt=1,,2", "an empty value"),
        ("scenario.dt=1,1.0,1", "listed twice"),
        ("scenario.dt=0:1:0", "num must be an integer >= 1"),
        ("scenario.dt=0:1:2.5", "num must be an integer >= 1"),
        ("scenario.dt=0:1:5:log", "log range needs start > 0"),
        ("scenario.dt=a:b:3", "a range is start:stop:num[:log] with numbers"),
        ("scenario.dt=1:inf:3", "start and stop must be finite numbers"),
        ("scenario.dt=1,inf", "not a finite number"),
        ("scenario.dt=1 2", "is not a TOML value"),
        ("scenario.dt={a = 1}", "a table cannot be a value"),
    ],
)
def test_bad_values_are_one_line(spec: str, fragment: str) -> None:
    with pytest.raises(FusionlogError, match="^--vary ") as e:
        parse_vary(spec)
    assert fragment in str(e.value) and "\n" not in str(e.value)


def test_keys_name_sensors_by_name_or_index_and_points_are_validated() -> None:
    points = grid_points(AJGL, [parse_vary("sensors.s2.R=1,4"), parse_vary("sensors[0].R=2")])
    assert [p.label for p in points] == [
        "sensors.s2.R=1, sensors[0].R=2",
        "sensors.s2.R=4, sensors[0].R=2",
    ]
    assert [float(p.scenario.system.sensors[1].R[0, 0]) for p in points] == [1.0, 4.0]
    assert all(float(p.scenario.system.sensors[0].R[0, 0]) == 2.0 for p in points)
    # each point has its own seed, derived from the file's seed and the point's index
    assert [p.scenario.seed for p in points] == [point_seed(2009, 0), point_seed(2009, 1)]
    # a key the file does not have yet (dropout) is added to its table
    (p,) = grid_points(AJGL, [parse_vary("sensors.s3.dropout=0.25")])
    assert p.scenario.system.sensors[2].timing.dropout == 0.25


@pytest.mark.parametrize(
    "vary, fragments",
    [
        ("sensors.s9.R=1", ["--vary sensors.s9.R", "no element 's9'", "s1, s2, s3"]),
        ("sensors.7.R=1", ["--vary sensors.7.R", "no element '7'"]),
        ("scenario.dt.x=1", ["scenario.dt is float 1", "no key 'x'"]),
        ("correlations.0.cov=0.1", ["no correlations array"]),
        ("scenario.dtt=1", ["[point 0: scenario.dtt=1]", "unknown key 'dtt'", "did you mean 'dt'"]),
        ("model.n0=0.1,-1", ["[point 1: model.n0=-1]", "model.n0: must be >= 0"]),
        ("sensors.s1.dropout=0.5,1.5", ["[point 1: sensors.s1.dropout=1.5]", "[0, 1)"]),
        ("sensors.s1.R=-1", ["[point 0: sensors.s1.R=-1]", "sensors[0].R"]),
    ],
)
def test_bad_keys_and_points_are_one_line_before_anything_runs(
    tmp_path: Path, vary: str, fragments: list[str]
) -> None:
    # --workers 2 would start a cluster: the grid is refused before that
    res = cli("sweep", AJGL, "--vary", vary, "--workers", "2", "--out-dir", tmp_path / "o")
    one_line_error(res, *fragments)
    assert not (tmp_path / "o").exists()


def test_usage_errors(tmp_path: Path) -> None:
    res = cli("sweep", AJGL, "--vary", "scenario.dt=1", "--workers", "1", "--scheduler", "x:1")
    assert res.exit_code == 2 and "give one of them" in res.stderr
    res = cli("sweep", AJGL, "--out-dir", tmp_path)
    assert res.exit_code == 2 and "--vary" in res.stderr
    ident = ROOT / "pipeline" / "aircraft_identity.toml"
    res = cli("sweep", ident, "--vary", "scenario.steps=5,6", "--exact-only", "--out-dir", tmp_path)
    one_line_error(res, "identity scenario", "state scenarios")


# ------------------------------------------------------------------------ merged metric sums


def test_merged_blocks_equal_one_accumulation() -> None:
    """Workers' block sums merged in block order are the sums of all runs in one go."""
    sc = scenario_with(load_scenario(AJGL), runs=900)
    job = Job(sc, ("CKF", "MSC"), "merge-test")
    parts = blocks(sc, 250)
    assert parts == [(0, 225), (225, 225), (450, 225), (675, 225)]  # equal, at most 250
    totals: dict = {}
    for off, n in parts:
        fold(totals, block_sums(job, off, n))
    x, _, est, _ = block_estimates(job, 0, 900)
    for a in job.archs:
        one = MetricsAccumulator(sc.instants, sc.system.n)
        one.add(x, est[a].mean, est[a].cov)
        r1, r2 = one.finalize(), totals[a].finalize()
        assert totals[a].runs == 900 and r1.mse_step.shape == r2.mse_step.shape
        for f in ("mse_step", "nees_step", "dm_step", "trace_step"):
            np.testing.assert_allclose(getattr(r2, f), getattr(r1, f), rtol=1e-12)
        assert r1.nees_fraction_inside == r2.nees_fraction_inside
        np.testing.assert_allclose(r2.stderr_mse, r1.stderr_mse, rtol=1e-9)


# ----------------------------------------------------------------------------- exact column


def test_exact_only_column_is_the_covariance_analysis_point_by_point(tmp_path: Path) -> None:
    d = tmp_path / "exact"
    res = ok(
        "sweep", AJGL, "--vary", "scenario.dt=0.1:3:4:log", "--exact-only", *ARCHS, "--out-dir", d
    )
    assert "exact analysis only" in res.stdout and "in this process" in res.stdout
    t = table(d)
    assert t.column_names == COLUMNS
    assert t.num_rows == 4 * 3
    assert t.column("runs").to_pylist() == [0] * 12
    assert t.column("mse").null_count == 12  # no Monte Carlo
    text = AJGL.read_text()
    for row in t.to_pylist():
        dt = row["scenario.dt"]
        sc = scenario_from_text(text.replace("dt = 1.0 ", f"dt = {dt!r} "))
        system = sc.system.on_times(sc.times)
        ex = analyse(build_plan(system, row["architecture"], sc.instants - 1), system)
        assert row["expected_mse"] == pytest.approx(ex.mse_per_state.mean(), rel=1e-12)
        assert row["expected_anees"] == pytest.approx(ex.nees.mean(), rel=1e-12)
    summary = json.loads((d / "summary.json").read_text())
    assert summary["kind"] == "sweep" and summary["exact_only"] is True
    assert summary["lowest_mse"]["CKF"]["by"] == "expected"


def test_dropout_points_have_the_conditional_expected_values_of_fusionlog_run(
    tmp_path: Path,
) -> None:
    """A point whose runs drop measurements has no exact analysis of its own: its expected
    values are the run averages of each run's, given its pattern, as `fusionlog run` reports
    them for the same runs; --exact-only has no runs, hence none."""
    d = tmp_path / "drop"
    ok("sweep", AJGL, "--vary", "sensors.s1.dropout=0,0.3", "--runs", "300", "--workers", "0",
       "--block-runs", "120", "--arch", "CKF", "--arch", "MSC", "--out-dir", d)  # fmt: skip
    rows = table(d).to_pylist()
    assert all(r["expected_mse"] is not None and r["mse"] is not None for r in rows)
    summary = json.loads((d / "summary.json").read_text())
    point = summary["points"][1]
    assert point["architectures"]["CKF"]["expected"]["conditional"] is True
    toml = tmp_path / "drop.toml"
    toml.write_text(AJGL.read_text().replace('name = "s1"', 'name = "s1"\ndropout = 0.3'))
    ok("run", toml, "--runs", "300", "--seed", str(point["seed"]), "--arch", "CKF", "--arch", "MSC",
       "--out-dir", tmp_path / "r")  # fmt: skip
    run = json.loads((tmp_path / "r" / "summary.json").read_text())["architectures"]
    for a in ("CKF", "MSC"):
        want, got = run[a], point["architectures"][a]
        assert want["expected"]["conditional"] is True
        for m in ("mse", "anees", "dm"):
            assert got["expected"][m] == pytest.approx(want["expected"][m], rel=1e-10), (a, m)
            assert got[m] == pytest.approx(want[m], rel=1e-10), (a, m)
    e = tmp_path / "exact"
    ok("sweep", AJGL, "--vary", "sensors.s1.dropout=0.3", "--exact-only", "--arch", "CKF",
       "--out-dir", e)  # fmt: skip
    assert table(e).column("expected_mse").to_pylist() == [None]


def test_distributed_run_with_dropouts_keeps_the_conditional_expected_values(
    tmp_path: Path,
) -> None:
    drop = ROOT / "pipeline" / "ajgl2009_dropout.toml"
    args = ("run", drop, "--runs", "400", "--block-runs", "150", "--arch", "CKF", "--arch", "FBS")
    ok(*args, "--out-dir", tmp_path / "local")
    ok(*args, "--workers", "0", "--out-dir", tmp_path / "dist")
    got = json.loads((tmp_path / "dist" / "summary.json").read_text())["architectures"]
    want = json.loads((tmp_path / "local" / "summary.json").read_text())["architectures"]
    for a in ("CKF", "FBS"):
        assert got[a]["expected"]["conditional"] is True
        for m in ("mse", "anees", "dm"):
            assert got[a]["expected"][m] == pytest.approx(want[a]["expected"][m], rel=1e-10)
            assert got[a][m] == pytest.approx(want[a][m], rel=1e-10)


def test_several_keys_make_the_product_and_a_line_per_other_value(tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    d = tmp_path / "two"
    ok("sweep", AJGL, "--vary", "scenario.dt=0.5,1,2", "--vary", "sensors.s1.R=1,4",
       "--exact-only", "--arch", "CKF", "--arch", "SKF", "--out-dir", d)  # fmt: skip
    t = table(d)
    assert t.column_names[:3] == ["scenario.dt", "sensors.s1.R", "architecture"]
    assert t.num_rows == 3 * 2 * 2
    assert t.column("sensors.s1.R").type == "int64"
    paths = {
        str(c.entity_path) for c in RrdReader(str(d / "sweep.rrd")).store().stream().to_chunks()
    }
    for line in ("CKF | sensors.s1.R=1", "CKF | sensors.s1.R=4", "SKF | sensors.s1.R=4"):
        assert "/" + entity_path("sweep", "mse", line, "exact") in paths, (line, sorted(paths))
    summary = ok("summary", d / "sweep.rrd").stdout
    assert "sensors.s1.R" in summary and "lowest MSE" in summary


def test_outputs_are_all_or_none_and_never_overwritten_without_force(tmp_path: Path) -> None:
    d = tmp_path / "o"
    args = ("sweep", AJGL, "--vary", "scenario.dt=1,2", "--exact-only", "--arch", "CKF")
    ok(*args, "--out-dir", d)
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    assert sorted(before) == ["summary.json", "sweep.parquet", "sweep.rrd"]
    (d / "sweep.rrd").unlink()  # only one output missing: the others still stop it
    one_line_error(cli(*args, "--out-dir", d), "sweep.parquet: exists", "--force")
    assert sorted(p.name for p in d.iterdir()) == ["summary.json", "sweep.parquet"]
    ok(*args, "--out-dir", d, "--force")
    assert sorted(p.name for p in d.iterdir()) == ["summary.json", "sweep.parquet", "sweep.rrd"]
    assert (d / "sweep.parquet").read_bytes() == before["sweep.parquet"]


# ---------------------------------------------------------------------- Dask: LocalCluster


@pytest.fixture(scope="module")
def in_process(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The reference table: every task in this process (--workers 0)."""
    d = tmp_path_factory.mktemp("sweep") / "w0"
    res = ok("sweep", AJGL, *SMALL, "--workers", "0", "--out-dir", d)
    assert "in this process" in res.stdout
    return d


@pytest.mark.parametrize("workers", [1, 2])
def test_local_cluster_gives_the_identical_table(in_process: Path, tmp_path: Path, workers) -> None:
    d = tmp_path / f"w{workers}"
    res = ok("sweep", AJGL, *SMALL, "--workers", str(workers), "--out-dir", d)
    assert f"LocalCluster of {workers} worker" in res.stdout
    assert res.stderr == ""  # no Dask log lines
    assert table(d).equals(table(in_process))
    assert (d / "summary.json").read_text() == (in_process / "summary.json").read_text()


def test_a_point_is_fusionlog_run_with_the_point_seed(in_process: Path, tmp_path: Path) -> None:
    rows = [r for r in table(in_process).to_pylist() if r["scenario.dt"] == 2.0]
    summary = json.loads((in_process / "summary.json").read_text())
    # Computed here from the contract, not by the code under test: SeedSequence(seed,
    # spawn_key=(point,)), its first 64-bit word shifted to 63 bits (a TOML integer).
    want = [
        int(np.random.SeedSequence(2009, spawn_key=(i,)).generate_state(1, np.uint64)[0]) >> 1
        for i in range(len(summary["points"]))
    ]
    assert [p["seed"] for p in summary["points"]] == want
    assert len(set(want)) == len(want) > 1  # every point its own runs
    seed = summary["points"][1]["seed"]
    toml = tmp_path / "dt2.toml"
    toml.write_text(AJGL.read_text().replace("dt = 1.0 ", "dt = 2.0 "))
    ok("run", toml, "--runs", "2500", "--seed", str(seed), *ARCHS, "--out-dir", tmp_path / "r")
    run = json.loads((tmp_path / "r" / "summary.json").read_text())["architectures"]
    for r in rows:
        want = run[r["architecture"]]
        for m in ("mse", "anees", "dm", "nees_fraction_inside"):
            assert r[m] == pytest.approx(want[m], rel=1e-10), (r["architecture"], m)
        assert r["expected_mse"] == pytest.approx(want["expected"]["mse"], rel=1e-12)


# ------------------------------------------------------- Dask: a real scheduler and workers


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real scheduler and two workers on 127.0.0.1 (`dask_cluster.loopback_cluster`)."""
    with loopback_cluster(tmp_path_factory.mktemp("dask")) as (address, _, _):
        yield address


def test_sweep_on_a_running_scheduler_gives_the_identical_table(
    scheduler: str, in_process: Path, tmp_path: Path
) -> None:
    d = tmp_path / "sched"
    res = ok("sweep", AJGL, *SMALL, "--scheduler", scheduler, "--out-dir", d)
    assert f"on the Dask scheduler at {scheduler} (2 workers, 2 threads)" in res.stdout
    assert table(d).equals(table(in_process))


def test_run_on_a_running_scheduler_writes_the_evaluation_only(
    scheduler: str, tmp_path: Path
) -> None:
    args = ("run", AJGL, "--runs", "2400", "--block-runs", "700", *ARCHS)
    ok(*args, "--out-dir", tmp_path / "local")
    res = ok(*args, "--scheduler", scheduler, "--out-dir", tmp_path / "dist")
    assert sorted(p.name for p in (tmp_path / "dist").iterdir()) == [
        "evaluation.rrd",
        "summary.json",
    ]
    assert "CKF" in res.stdout and scheduler in res.stdout
    ok("compare", tmp_path / "dist" / "summary.json", tmp_path / "local" / "summary.json",
       "--rtol", "1e-9")  # fmt: skip
    from fusionlog.io.rrd import read_recording

    rec = read_recording(tmp_path / "dist" / "evaluation.rrd")
    local = read_recording(tmp_path / "local" / "evaluation.rrd")
    # the sample runs are the same runs, computed here
    for key in ("runs/0/position/truth", "runs/2/velocity/MSC/mean", "metrics/nees/SKF"):
        np.testing.assert_allclose(rec["series"][key], local["series"][key], rtol=1e-9)


def test_unreachable_scheduler_is_one_line(tmp_path: Path) -> None:
    res = cli("sweep", AJGL, "--vary", "scenario.dt=1", "--runs", "10", "--arch", "CKF",
              "--scheduler", f"tcp://127.0.0.1:{free_port()}", "--scheduler-timeout", "2",
              "--out-dir", tmp_path)  # fmt: skip
    one_line_error(res, "--scheduler tcp://127.0.0.1:", "cannot connect")


# ------------------------------------------------------------------- signals, start-up cost


def _is_worker(child: psutil.Process, command: psutil.Process) -> bool:
    """A LocalCluster worker of `command`: forked (Linux: the command's own command line) or
    spawned (multiprocessing's spawn_main); not the short-lived helpers some imports run."""
    try:
        line = child.cmdline()
    except psutil.Error:  # gone, or a zombie not yet reaped
        return False
    return line == command.cmdline() or "spawn_main" in " ".join(line)


@pytest.mark.parametrize(("workers", "pause"), [(1, 1.0), (2, 0.0)])
def test_sigterm_cancels_the_cluster_and_leaves_nothing(
    tmp_path: Path, workers: int, pause: float
) -> None:
    """SIGTERM while the runs are computed, or as soon as a worker process exists (at times
    while the workers are still being started: held until they are up, then the same
    unwinding): the same one line, nothing left behind, no worker left."""
    d = tmp_path / "killed"
    cmd = [str(BIN / "fusionlog"), "sweep", str(AJGL), "--vary", "scenario.dt=0.5,1,2",
           "--runs", "2000000", "--workers", str(workers), "--out-dir", str(d)]  # fmt: skip
    proc = subprocess.Popen(cmd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        me = psutil.Process(proc.pid)
        deadline = time.monotonic() + 60
        found: list[psutil.Process] = []
        while time.monotonic() < deadline and not found:  # wait for a worker process
            found = [c for c in me.children(recursive=True) if _is_worker(c, me)]
            time.sleep(0.2 if pause else 0.005)
        assert found, "no worker process started"
        time.sleep(pause)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.decode().splitlines() == [
        "fusionlog: interrupted; no partial output was left behind"
    ]
    assert not d.exists() or not any(d.iterdir())
    gone, alive = psutil.wait_procs(found, timeout=10)
    assert not alive, "the LocalCluster's workers outlived the command"


def test_importing_the_cli_does_not_import_dask() -> None:
    heavy = "('dask', 'distributed', 'pyarrow')"
    code = f"import sys, fusionlog.cli; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV)
    assert out.stdout.strip() == "[]", out.stderr


def test_compare_gates_a_sweep_summary_point_by_point(tmp_path: Path) -> None:
    """DESIGN.md: `compare SUMMARY.json GOLDEN.json` on the summary.json a sweep writes (it was
    refused as "not a fusionlog summary", exit 2): equal 0, a moved point 1 with its key path,
    a malformed point 2."""
    ok("sweep", AJGL, "--vary", "scenario.dt=1,2", "--runs", "20", *ARCHS, "--out-dir", tmp_path)
    golden = tmp_path / "summary.json"
    ok("compare", golden, golden)
    doc = json.loads(golden.read_text())
    doc["points"][1]["architectures"]["MSC"]["anees"] *= 1.05
    moved = tmp_path / "moved.json"
    moved.write_text(json.dumps(doc))
    res = cli("compare", moved, golden)
    assert res.exit_code == 1 and "points[1].architectures.MSC.anees" in res.stdout, res.output
    assert cli("compare", moved, golden, "--rtol", "0.1").exit_code == 0
    doc["points"][0]["architectures"]["CKF"]["mse"] = "0.2"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    one_line_error(cli("compare", bad, golden), str(bad), "points[0]", "architectures.CKF.mse")
