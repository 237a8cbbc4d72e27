"""docs/tutorials/trajectory-metrics.md, run: its replay file on evo's ROS_example.bag
(`../shared/data/logs/evo_ROS_example.bag`, linked into a temporary folder under the name the
tutorial uses; skipped without it), the numbers it prints against the summaries, and the
summaries against evo's APE and RPE (its Python API) on the files `fusionlog export` writes."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

evo_io = pytest.importorskip("evo.tools.file_interface")
evo_metrics = pytest.importorskip("evo.core.metrics")
evo_sync = pytest.importorskip("evo.core.sync")
evo_traj = pytest.importorskip("evo.core.trajectory")

REPO = Path(__file__).resolve().parent.parent
DOC = REPO / "docs" / "tutorials" / "trajectory-metrics.md"
BAG = REPO.parent / "shared" / "data" / "logs" / "evo_ROS_example.bag"


def _evo_ape(ref, est, align: str) -> float:
    r, e = evo_sync.associate_trajectories(ref, est)
    if align != "none":
        e.align(r, correct_scale=align == "similarity")
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((r, e))
    return ape.get_statistic(evo_metrics.StatisticsType.rmse)


@pytest.mark.skipif(not BAG.exists(), reason="evo's example bag is not in ../shared/data/logs")
def test_the_walkthrough_on_evos_bag(tmp_path, monkeypatch):
    doc = DOC.read_text()
    toml = re.search(r"```toml\n(.*?)```", doc, re.S).group(1)
    (tmp_path / "evo_example.toml").write_text(toml)
    (tmp_path / "ROS_example.bag").symlink_to(BAG)
    monkeypatch.chdir(tmp_path)
    printed = ok("run", "evo_example.toml", "--out-dir", "out").stdout
    summaries = {"none": json.loads(Path("out/summary.json").read_text())}
    for align in ("rigid", "similarity"):
        res = ok("evaluate", "out/sensors.mcap", "out/estimates.mcap", "-o", f"out/{align}.rrd",
                 "--summary", f"out/{align}.json", "--align", align)  # fmt: skip
        printed += res.stdout
        summaries[align] = json.loads(Path(f"out/{align}.json").read_text())
    # the tutorial's table and printed lines are what the commands print
    for align, s in summaries.items():
        e = s["architectures"]["CKF"]
        row = f"| `{align}`".ljust(15) + f"| {e['mse']:.4f}  | {e['ape']['rmse']:.4f}"
        assert row + f"       | {e['rpe']['rmse']:.4f}       |" in doc, align
        assert e["ape"]["align"] == align
    for line in re.findall(r"^CKF: \w+ alignment: .*$", doc, re.M):
        assert line in printed
    # evo on the exported files
    ok("export", "out/estimates.mcap", "--arch", "CKF", "--format", "tum", "-o", "ckf.tum")
    ok("export", "out/sensors.mcap", "--truth", "--format", "tum", "-o", "truth.tum")
    ref, est = (evo_io.read_tum_trajectory_file(f) for f in ("truth.tum", "ckf.tum"))
    assert ref.num_poses == summaries["none"]["truth"]["matched"]
    for align, flag in (("rigid", "-a"), ("similarity", "-as")):
        theirs = _evo_ape(ref, est, align)
        assert summaries[align]["architectures"]["CKF"]["ape"]["rmse"] == pytest.approx(
            theirs, rel=1e-9
        )
        assert re.search(rf"evo_ape tum truth.tum ckf.tum {flag} +# rmse {theirs:.6f} ", doc)
    r, e = evo_sync.associate_trajectories(ref, est)
    rpe = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, 1, evo_metrics.Unit.frames)
    rpe.process_data((r, e))
    rmse = rpe.get_statistic(evo_metrics.StatisticsType.rmse)
    assert summaries["none"]["architectures"]["CKF"]["rpe"]["rmse"] == pytest.approx(rmse, rel=1e-9)
    assert f"# rmse {rmse:.6f}" in doc
    # evo's RPE of relative poses is blind to the rigid alignment (identity orientations turned
    # with the positions): the tutorial's claim
    e2 = evo_traj.PoseTrajectory3D(e.positions_xyz, e.orientations_quat_wxyz, e.timestamps)
    e2.align(r)
    rpe2 = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, 1, evo_metrics.Unit.frames)
    rpe2.process_data((r, e2))
    assert rpe2.get_statistic(evo_metrics.StatisticsType.rmse) == pytest.approx(rmse, rel=1e-9)
    assert np.isfinite(rmse)
