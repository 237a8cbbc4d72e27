"""Issue 33, trajectory metrics and interchange (DESIGN.md "Trajectory metrics"): Umeyama's
alignment against a constructed similarity, APE/RPE against evo's own implementation (its
Python API, GPL: a test-only dependency), the pipeline's summary against evo on the files
`fusionlog export` writes, the exported files read back, `align = "none"` leaving every other
number as it was, and the one-line errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, ok, one_line_error

import fusionlog as fl
from fusionlog.core.trajectory import (
    AlignmentError,
    TrajectorySettings,
    error_statistics,
    run_trajectory,
    umeyama,
)
from fusionlog.io.mcap import McapFile

evo_traj = pytest.importorskip("evo.core.trajectory")
evo_metrics = pytest.importorskip("evo.core.metrics")
evo_io = pytest.importorskip("evo.tools.file_interface")
evo_sync = pytest.importorskip("evo.core.sync")

REPO = Path(__file__).resolve().parent.parent


def rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """R = I + sin θ K + (1 − cos θ) K², K the cross-product matrix of the unit axis."""
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@pytest.mark.parametrize("m", [2, 3])
def test_umeyama_recovers_a_constructed_similarity(m):
    rng = np.random.default_rng(5)
    p = rng.normal(scale=10.0, size=(40, m))
    if m == 3:
        R = rodrigues(np.array([0.3, -0.5, 0.8]), 0.7)
    else:
        th = 0.7
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    t, c = rng.normal(scale=100.0, size=m), 2.5
    g = c * p @ R.T + t  # exact: the fit must return (c, R, t) to rounding
    a = umeyama(p, g, with_scale=True)
    # |p| ~ 30, |t| ~ 100: rounding of the means and the SVD at ~1e-13 relative
    np.testing.assert_allclose(a.rotation, R, atol=1e-12)
    assert a.scale == pytest.approx(c, rel=1e-12)
    np.testing.assert_allclose(a.translation, t, rtol=0, atol=1e-10)
    rigid = umeyama(p, g, with_scale=False)
    np.testing.assert_allclose(rigid.rotation, R, atol=1e-12)  # the rotation does not need c
    assert rigid.scale == 1.0


def test_umeyama_refuses_collinear_points_in_3d():
    s = np.linspace(0, 10, 20)[:, None]
    line = s * np.array([1.0, 2.0, 3.0])
    with pytest.raises(AlignmentError, match="collinear"):
        umeyama(line, line + 1.0, with_scale=False)


def _evo(p, g, t, align, delta, unit):
    """evo's APE and RPE (translation part) of positions p on truth g at times t: evo aligns
    (Umeyama / origin) and measures; RPE on the aligned positions with identity orientation
    (DESIGN.md: evo's definitions for positions)."""
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
    ref, est = evo_traj.PoseTrajectory3D(g, q, t), evo_traj.PoseTrajectory3D(p, q, t)
    if align == "rigid":
        est.align(ref)
    elif align == "similarity":
        est.align(ref, correct_scale=True)
    elif align == "origin":
        est.align_origin(ref)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    flat = evo_traj.PoseTrajectory3D(est.positions_xyz, q, t)
    u = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
    rpe = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, delta, u, all_pairs=False)
    rpe.process_data((ref, flat))
    return ape, rpe


@pytest.mark.parametrize("align", ["none", "origin", "rigid", "similarity"])
@pytest.mark.parametrize(("delta", "unit"), [(1, "frames"), (7, "frames"), (4.0, "m")])
def test_ape_and_rpe_equal_evos(align, delta, unit):
    rng = np.random.default_rng(11)
    n = 300
    t = np.arange(n) * 0.1
    g = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    R = rodrigues(np.array([0.1, 0.2, 1.0]), 0.25)
    p = 1.2 * g @ R.T + [3.0, -2.0, 1.0] + rng.normal(scale=0.3, size=(n, 3))
    ape, rpe = _evo(p, g, t, align, delta, unit)
    rt = run_trajectory(p, g, t, TrajectorySettings((0, 1, 2), align, None, delta, unit))
    assert len(rt.rpe) == len(rpe.error)
    ours, theirs = error_statistics(rt.ape), ape.get_all_statistics()
    # the errors are O(1) differences of O(10) positions: rounding ~1e-14 relative
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[k] == pytest.approx(theirs[k], rel=1e-9, abs=1e-12), k
    ours, theirs = error_statistics(rt.rpe), rpe.get_all_statistics()
    for k in ("rmse", "mean", "median", "std", "min", "max"):
        assert ours[k] == pytest.approx(theirs[k], rel=1e-9, abs=1e-12), k


def test_rpe_in_seconds_pairs_each_instant_with_the_first_delta_later():
    """rpe_unit = "s" (evo has none): pairs i -> the first instant at least delta seconds on,
    written here from the definition on irregular instants."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.05, 0.4, size=80))
    g = np.cumsum(rng.normal(size=(80, 2)), axis=0)
    p = g + rng.normal(scale=0.2, size=(80, 2))
    rt = run_trajectory(p, g, t, TrajectorySettings((0, 1), "none", None, 1.0, "s"))
    ids = [0]
    while True:
        later = [k for k in range(ids[-1] + 1, len(t)) if t[k] - t[ids[-1]] >= 1.0 - 1e-9]
        if not later:
            break
        ids.append(later[0])
    pairs = zip(ids[:-1], ids[1:], strict=True)
    want = [np.linalg.norm((p[j] - p[i]) - (g[j] - g[i])) for i, j in pairs]
    np.testing.assert_allclose(rt.rpe, want, rtol=1e-12)
    np.testing.assert_array_equal(rt.rpe_at, ids[1:])


SCENARIO = """
[scenario]
name = "walk3d"
steps = {steps}
runs = {runs}
seed = 4
dt = 1.0
state_names = ["x", "vx", "y", "vy", "z", "vz"]

[model]
kind = "constant-velocity"
axes = 3
n0 = 0.5

[prior]
mean = [0.0, 1.0, 0.0, 0.5, 0.0, -0.2]
cov = [[4.0,0,0,0,0,0],[0,1.0,0,0,0,0],[0,0,4.0,0,0,0],
       [0,0,0,1.0,0,0],[0,0,0,0,4.0,0],[0,0,0,0,0,1.0]]

[[sensors]]
name = "pos"
H = [[1.0,0,0,0,0,0],[0,0,1.0,0,0,0],[0,0,0,0,1.0,0]]
R = [[1.0,0,0],[0,1.0,0],[0,0,1.0]]

[estimate]
architectures = ["CKF", "SKF"]

[evaluate]
sample_runs = 1
{evaluate}
"""


def _scenario(tmp_path: Path, evaluate: str = "", steps: int = 60, runs: int = 1) -> Path:
    f = tmp_path / f"walk3d_{abs(hash(evaluate)) % 10**8}_{steps}_{runs}.toml"
    f.write_text(SCENARIO.format(evaluate=evaluate, steps=steps, runs=runs))
    return f


def _run(tmp_path: Path, scenario: Path, *args: str) -> tuple[Path, dict]:
    out = tmp_path / f"out-{scenario.stem}-{'-'.join(args) or 'default'}"
    ok("run", scenario, "--out-dir", out, "--force", *args)
    return out, json.loads((out / "summary.json").read_text())


@pytest.mark.parametrize("align", ["rigid", "similarity"])
def test_the_summary_equals_evo_on_the_exported_files(tmp_path, align):
    """`fusionlog run` then `export` of the truth and each estimate as TUM: evo reads them,
    aligns and measures; its APE and RPE equal summary.json's."""
    sc = _scenario(tmp_path, "rpe_delta = 3\nalign_first = 40")
    out, summary = _run(tmp_path, sc, "--align", align)
    ok("export", out / "sensors.mcap", "--truth", "--format", "tum", "-o", out / "truth.txt")
    ref = evo_io.read_tum_trajectory_file(str(out / "truth.txt"))
    for arch in ("CKF", "SKF"):
        f = out / f"{arch}.txt"
        ok("export", out / "estimates.mcap", "--arch", arch, "--format", "tum", "-o", f)
        est = evo_io.read_tum_trajectory_file(str(f))
        r, e = evo_sync.associate_trajectories(ref, est)
        e.align(r, correct_scale=align == "similarity", n=40)
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((r, e))
        q = np.tile([1.0, 0, 0, 0], (e.num_poses, 1))
        flat = evo_traj.PoseTrajectory3D(e.positions_xyz, q, e.timestamps)
        rpe = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, 3, evo_metrics.Unit.frames)
        rpe.process_data((r, flat))
        got = summary["architectures"][arch]
        assert got["ape"]["align"] == align and got["rpe"]["pairs"] == len(rpe.error)
        for k, v in ape.get_all_statistics().items():
            if k != "sse":
                assert got["ape"][k] == pytest.approx(v, rel=1e-9), (arch, k)
        for k, v in rpe.get_all_statistics().items():
            if k != "sse":
                assert got["rpe"][k] == pytest.approx(v, rel=1e-9), (arch, k)


def test_exported_files_read_back_equal_the_estimates(tmp_path):
    sc = _scenario(tmp_path)
    out, _ = _run(tmp_path, sc)
    mean, cov = McapFile(out / "estimates.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    times = McapFile(out / "estimates.mcap").times()
    pos = mean[0][:, [0, 2, 4]]
    ok("export", out / "estimates.mcap", "--arch", "CKF", "--format", "tum", "-o", out / "c.tum")
    tum = evo_io.read_tum_trajectory_file(str(out / "c.tum"))
    np.testing.assert_array_equal(tum.positions_xyz, pos)  # repr: every bit
    np.testing.assert_array_equal(tum.timestamps, times)
    np.testing.assert_array_equal(tum.orientations_quat_wxyz, np.tile([1.0, 0, 0, 0], (61, 1)))
    ok(
        "export",
        out / "estimates.mcap",
        "--arch",
        "CKF",
        "--format",
        "kitti",
        "-o",
        out / "c.kitti",
    )
    kitti = evo_io.read_kitti_poses_file(str(out / "c.kitti"))
    np.testing.assert_array_equal(kitti.positions_xyz, pos)
    ok("export", out / "estimates.mcap", "--arch", "CKF", "--format", "csv", "-o", out / "c.csv")
    lines = (out / "c.csv").read_text().splitlines()
    names = ["x", "vx", "y", "vy", "z", "vz"]
    assert lines[0].split(",") == ["time"] + [c for s in names for c in (s, f"{s}_std")]
    table = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    np.testing.assert_array_equal(table[:, 1::2], mean[0])
    std = np.sqrt(np.diagonal(cov if cov.ndim == 3 else cov[0], axis1=-2, axis2=-1))
    np.testing.assert_array_equal(table[:, 2::2], std)
    assert (
        fl.export(out / "estimates.mcap", arch="CKF", format="tum") == (out / "c.tum").read_text()
    )


def test_align_none_leaves_every_other_number_as_it_was(tmp_path):
    """The trajectory metrics add ape/rpe and change nothing else, bit for bit; with align
    "none" the APE's rmse is the root of the position states' MSE summed (every instant
    matched, every run)."""
    plain, with_none, rigid = (
        _run(tmp_path, _scenario(tmp_path, ev, runs=30), *args)[1]
        for ev, args in (
            ("position_states = []", ()),
            ('align = "none"', ()),
            ("", ("--align", "rigid")),
        )
    )
    for s in (with_none, rigid):
        for a, e in s["architectures"].items():
            assert {k: v for k, v in e.items() if k not in ("ape", "rpe")} == plain[
                "architectures"
            ][a]
    for a, e in with_none["architectures"].items():
        assert "ape" not in plain["architectures"][a]
        mse = e["mse_per_state"]
        assert e["ape"]["rmse"] ** 2 == pytest.approx(mse[0] + mse[2] + mse[4], rel=1e-12)
        assert e["ape"]["rotation"] == np.eye(3).tolist() and e["ape"]["scale"] == 1.0
        assert rigid["architectures"][a]["ape"]["rotation"] is None  # one per run


def test_the_table_shows_ape_and_rpe_after_mse_and_the_alignment(tmp_path):
    res = ok("run", _scenario(tmp_path), "--out-dir", tmp_path / "o", "--align", "similarity")
    header = next(line for line in res.stdout.splitlines() if line.startswith("architecture"))
    assert header.split()[:4] == ["architecture", "MSE", "APE", "RPE"]
    assert any(
        line.startswith("CKF: similarity alignment: rotation ") for line in res.stdout.splitlines()
    )


def test_bad_input_is_one_line(tmp_path):
    bad = _scenario(tmp_path, 'position_states = ["x", "w"]')
    one_line_error(
        cli("run", bad, "--out-dir", tmp_path / "b"), "evaluate.position_states[1]", "'w'"
    )
    short = _scenario(tmp_path, "", steps=1)
    one_line_error(
        cli("run", short, "--out-dir", tmp_path / "s", "--align", "rigid"),
        "2 matched instant",
        "at least 3",
    )
    out, _ = _run(tmp_path, _scenario(tmp_path))
    est = out / "estimates.mcap"
    one_line_error(
        cli("export", est, "--arch", "MSC", "--format", "tum", "-o", tmp_path / "x"),
        "no architecture 'MSC'",
    )
    one_line_error(
        cli("export", est, "--arch", "CKF", "--run", "1", "--format", "tum", "-o", tmp_path / "x"),
        "no run 1",
    )
    one_line_error(
        cli("export", est, "--arch", "CKF", "--format", "tum", "-o", est, "--force"), "input"
    )
    one_line_error(
        cli("export", est, "--truth", "--format", "tum", "-o", tmp_path / "x"), "no /truth"
    )
    (tmp_path / "x").write_text("keep")
    one_line_error(
        cli("export", est, "--arch", "CKF", "--format", "csv", "-o", tmp_path / "x"), "exists"
    )
    assert (tmp_path / "x").read_text() == "keep"


def test_a_collinear_truth_cannot_be_aligned_rigidly(tmp_path):
    """The truth moves along x only (no process noise on y and z, which start known): the
    Umeyama covariance has rank 1 in 3-D, the rotation is not determined."""
    text = """
[scenario]
name = "line"
steps = 30
runs = 1
seed = 1
dt = 1.0
state_names = ["x", "y", "z"]
[model]
F = [[1.0,0,0],[0,1.0,0],[0,0,1.0]]
Q = [[1.0,0,0],[0,0,0],[0,0,0]]
[prior]
mean = [0.0, 0.0, 0.0]
cov = [[1.0,0,0],[0,1.0,0],[0,0,1.0]]
[truth]
initial_mean = [0.0, 0.0, 0.0]
initial_cov = [[1.0,0,0],[0,0,0],[0,0,0]]
[[sensors]]
name = "p"
H = [[1.0,0,0],[0,1.0,0],[0,0,1.0]]
R = [[1.0,0,0],[0,1.0,0],[0,0,1.0]]
[estimate]
architectures = ["CKF"]
[evaluate]
align = "rigid"
"""
    f = tmp_path / "line.toml"
    f.write_text(text)
    one_line_error(cli("run", f, "--out-dir", tmp_path / "o"), "CKF", "collinear")


@pytest.mark.parametrize("gap", [False, True])
def test_runs_are_measured_one_by_one_and_averaged(gap):
    """Over M runs each run is aligned and measured on its own (evo, per run, here) and the
    summary is the documented aggregate: rmse the root mean of the runs' squared rmse, min and
    max the extremes, the others the mean over runs; APE over time the mean over the runs at
    each instant. With `gap` one run misses an instant (it is then measured alone)."""
    from fusionlog.core.trajectory import block_sums

    rng = np.random.default_rng(8)
    M, K1 = 6, 40
    t = np.arange(K1) * 0.5
    truth = np.cumsum(rng.normal(size=(M, K1, 4)), axis=1)
    est = truth + rng.normal(scale=0.4, size=truth.shape) + [1.0, 0.0, -2.0, 0.0]
    if gap:
        est[3, 7] = np.nan
    s = TrajectorySettings((0, 2), "similarity", None, 2, "frames")
    sums = block_sums(s, t, truth, {"A": est}, run_offset=0)["A"]
    ape, rpe = sums.summary()
    per_run, per_run_rpe, at = [], [], np.zeros(K1)
    count = np.zeros(K1)
    for r in range(M):
        ok_ = np.isfinite(est[r]).all(axis=1)
        p3 = np.zeros((ok_.sum(), 3))
        g3 = np.zeros((ok_.sum(), 3))
        p3[:, :2], g3[:, :2] = est[r][ok_][:, [0, 2]], truth[r][ok_][:, [0, 2]]
        a, b = _evo(p3, g3, t[ok_], "similarity", 2, "frames")
        per_run.append(a.get_all_statistics())
        per_run_rpe.append(b.get_all_statistics())
        at[ok_] += a.error
        count[ok_] += 1
    for got, runs in ((ape, per_run), (rpe, per_run_rpe)):
        want = {k: np.mean([x[k] for x in runs]) for k in ("mean", "median", "std")}
        want["rmse"] = math.sqrt(np.mean([x["rmse"] ** 2 for x in runs]))
        want["min"] = min(x["min"] for x in runs)
        want["max"] = max(x["max"] for x in runs)
        for k, v in want.items():
            assert got[k] == pytest.approx(v, rel=1e-9), k
    assert ape["rotation"] is None and ape["scale"] is None  # one per run
    np.testing.assert_allclose(sums.series()["ape"], at / count, rtol=1e-9)


def test_distributed_runs_and_sweeps_carry_the_trajectory_metrics(tmp_path):
    sc = _scenario(tmp_path, 'align = "rigid"', runs=40)
    _, plain = _run(tmp_path, sc)
    _, spread = _run(tmp_path, sc, "--workers", "0", "--block-runs", "7")
    for a, e in plain["architectures"].items():
        for key in ("ape", "rpe"):
            for k, v in e[key].items():
                if isinstance(v, float):
                    assert spread["architectures"][a][key][k] == pytest.approx(v, rel=1e-12)
    out = tmp_path / "sweep"
    ok("sweep", sc, "--vary", "model.n0=0.1,0.5", "--runs", "20", "--out-dir", out)
    import pyarrow.parquet as pq

    table = pq.read_table(out / "sweep.parquet").to_pylist()
    summary = json.loads((out / "summary.json").read_text())
    for row in table:
        point = next(p for p in summary["points"] if p["values"]["model.n0"] == row["model.n0"])
        e = point["architectures"][row["architecture"]]
        assert row["ape_rmse"] == e["ape"]["rmse"] and row["rpe_rmse"] == e["rpe"]["rmse"]
        assert row["ape_rmse"] > 0


def test_the_recording_has_ape_and_rpe_over_time(tmp_path):
    from fusionlog.io.rrd.read import read_recording

    out, summary = _run(tmp_path, _scenario(tmp_path), "--align", "rigid")
    rec = read_recording(out / "evaluation.rrd")
    for a, e in summary["architectures"].items():
        ape = rec["series"][f"metrics/ape/{a}"]
        assert math.sqrt(np.nanmean(ape**2)) == pytest.approx(e["ape"]["rmse"], rel=1e-12)
        rpe = rec["series"][f"metrics/rpe/{a}"]
        assert np.count_nonzero(np.isfinite(rpe)) == e["rpe"]["pairs"]


def test_the_api_export_writes_only_when_asked_and_names_its_arguments(tmp_path, monkeypatch):
    out, _ = _run(tmp_path, _scenario(tmp_path))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.chdir(scratch)
    text = fl.export(out / "estimates.mcap", arch="SKF", format="csv")
    assert text.startswith("time,x,x_std") and list(scratch.iterdir()) == []
    assert fl.export(out / "estimates.mcap", "s.csv", arch="SKF", format="csv") == text
    assert (scratch / "s.csv").read_text() == text
    with pytest.raises(fl.FusionlogError, match="exists"):
        fl.export(out / "estimates.mcap", "s.csv", arch="SKF", format="csv")
    for kw, msg in (
        ({"arch": "SKF", "format": "xyz"}, "^format: unknown format 'xyz'"),
        ({"arch": "SKF", "run": -1}, "^run: expected an integer >= 0"),
        ({"arch": "SKF", "run": True}, "^run: "),
        ({"arch": "nope"}, "no architecture 'nope'"),
    ):
        with pytest.raises(fl.FusionlogError, match=msg):
            fl.export(out / "estimates.mcap", **kw)


def test_positions_near_the_largest_double_give_inf_not_a_warning():
    """(The suite turns numpy warnings into errors.) APE of positions ±1e308 apart is inf; a
    fit whose moments overflow is refused as an AlignmentError naming the run."""
    from fusionlog.core.trajectory import block_sums

    x = np.array([[[1e308, 1e308], [-1e308, 2.0], [3.0, 1e308], [1.0, 2.0]]])
    ape, _ = block_sums(TrajectorySettings((0, 1)), np.arange(4.0), x, {"A": -x})["A"].summary()
    assert ape["max"] == math.inf
    with pytest.raises(AlignmentError, match="^A: run 0: positions too large"):
        block_sums(TrajectorySettings((0, 1), "rigid"), np.arange(4.0), x, {"A": -x})


def test_a_replays_exports_carry_the_recordings_clock(tmp_path):
    """DESIGN.md "MCAP files": a replay's estimates keep the recording's log_time; export
    writes it (exact decimal seconds) for the estimates and the truth alike, read here with
    the plain mcap reader."""
    from mcap.reader import make_reader

    out = tmp_path / "tum"
    ok("run", REPO / "pipeline" / "replay_tum.toml", "--out-dir", out)

    def stamps(path, prefix):
        with open(path, "rb") as f:
            reader = make_reader(f)
            return sorted(
                {m.log_time for _, c, m in reader.iter_messages() if c.topic.startswith(prefix)}
            )

    sensors, estimates = (
        stamps(out / "sensors.mcap", "/sensors/"),
        stamps(out / "estimates.mcap", "/estimates/"),
    )
    assert estimates == sensors and sensors[0] > 10**18  # 2011, in ns
    ok("export", out / "estimates.mcap", "--arch", "CKF", "--format", "tum", "-o", out / "e.tum")
    first = [line.split()[0] for line in (out / "e.tum").read_text().splitlines()]
    assert first == [f"{t // 10**9}.{t % 10**9:09d}" for t in sensors]


def test_the_recording_toggles_between_aligned_and_raw_paths(tmp_path):
    """Run 0's truth and paths, aligned and raw, as static strips, in the plane of the two
    position states the truth spreads most along, with the aligned points = R p + t of the
    summary's alignment (one run: its own)."""
    from rerun.chunk import RrdReader

    out, summary = _run(tmp_path, _scenario(tmp_path, 'position_states = ["x", "y", "z"]'),
                        "--align", "rigid")  # fmt: skip
    reader = RrdReader(str(out / "evaluation.rrd"))
    strips, names = {}, set()
    for ch in reader.store().stream().to_chunks():
        batch = ch.to_record_batch()
        if ch.is_static and "LineStrips2D:strips" in batch.schema.names:
            strips[str(ch.entity_path)] = np.array(
                batch.column("LineStrips2D:strips").to_pylist()[0][0]
            )
    for ch in reader.store(store=reader.blueprints()[0]).stream().to_chunks():
        batch = ch.to_record_batch()
        if "ViewBlueprint:display_name" in batch.schema.names:
            names.add(batch.column("ViewBlueprint:display_name").to_pylist()[0][0])
    for e in ("/aligned/truth", "/aligned/CKF", "/raw/truth", "/raw/CKF", "/aligned/SKF"):
        assert e in strips, e
    truth = McapFile(out / "sensors.mcap").read_all(["/truth"])["/truth"]
    g = truth[0][:, [0, 2, 4]]
    cols = sorted(np.argsort(-g.var(axis=0), kind="stable")[:2])
    mean, _ = McapFile(out / "estimates.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    ape = summary["architectures"]["CKF"]["ape"]
    R, t = np.array(ape["rotation"]), np.array(ape["translation"])
    aligned = mean[0][:, [0, 2, 4]] @ R.T + t
    # Rerun stores 2-D points in float32
    np.testing.assert_allclose(strips["/aligned/CKF"], aligned[:, cols], rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(
        strips["/raw/CKF"], mean[0][:, [0, 2, 4]][:, cols], rtol=1e-6, atol=1e-5
    )
    xyz = ["x", "y", "z"]
    assert f"Trajectory: aligned ({xyz[cols[0]]}, {xyz[cols[1]]})" in names
    assert f"Trajectory: raw ({xyz[cols[0]]}, {xyz[cols[1]]})" in names
