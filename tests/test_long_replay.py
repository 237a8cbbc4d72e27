"""Issue 34: a recorded replay in blocks of time -- irregular instants, a covariance per message,
sensors absent at most instants, a truth of some states only -- through the plan-free replay
path carried from block to block (`core.architectures.replay_blocks`, the exact one-log route
`core.exact_replay.ExpectedBlocks`, the evaluate stage's `long_*` parts).

The time-block size is the hidden setting FUSIONLOG_TIME_BLOCK, so that replay_robot's 2292
instants span five blocks. Blocked and whole runs compute the same recursions instant by instant
in the same order (only the blocks' batched products change), so they agree to rounding: the
filters are contractive, a rounding does not grow along the log; 1e-9 relative bounds what
summing a few thousand instants in another grouping can move (1e-13 each).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

from fusionlog.io.mcap import McapFile
from fusionlog.io.rrd import read_recording

ROOT = Path(__file__).resolve().parents[1]
ROBOT = ROOT / "pipeline" / "replay_robot.toml"
ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:pose", "CI", "FBS", "AVG", "SKF:odom"]
RTOL = 1e-9


def _robot_partial(folder: Path) -> Path:
    """replay_robot (ROS 2 odometry at ~30 Hz and localiser poses at ~1 Hz with a covariance
    per message, a 20 Hz motion-capture CSV: irregular instants, at each one or two sensors
    present) with a partial truth: the positions alone, the states renamed so that no
    trajectory metrics are asked for (longer logs' APE/RPE are another part's business)."""
    text = ROBOT.read_text()
    data = (ROOT / "pipeline" / "data").resolve()
    for a, b in (
        ('state_names = ["x", "vx", "y", "vy"]', 'state_names = ["px", "vx", "py", "vy"]'),
        ('source = "data/', f'source = "{data}/'),
        ('values = ["x [m]", "y [m]", "vx [m s^-1]", "vy [m s^-1]"]', 'values = ["x [m]", "y [m]"]'),
        ('states = ["x", "y", "vx", "vy"]', 'states = ["px", "py"]'),
        ('architectures = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:mocap", "CI", "FBS"]',
         f"architectures = {json.dumps(ARCHS)}"),
    ):  # fmt: skip
        assert a in text, a
        text = text.replace(a, b)
    path = folder / "robot.toml"
    path.write_text(text)
    return path


def _close(a, b, path=""):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        same = math.isnan(a) and math.isnan(b)
        assert same or math.isclose(a, b, rel_tol=RTOL, abs_tol=1e-12), (path, a, b)
    else:
        assert a == b, (path, a, b)


@pytest.fixture(scope="module")
def robot_runs(tmp_path_factory):
    """The replay run whole and in blocks of 500 instants."""
    tmp = tmp_path_factory.mktemp("long_replay")
    replay = _robot_partial(tmp)
    mp = pytest.MonkeyPatch()
    outs = []
    try:
        for name, block in (("whole", None), ("blocked", "500")):
            if block is None:
                mp.delenv("FUSIONLOG_TIME_BLOCK", raising=False)
            else:
                mp.setenv("FUSIONLOG_TIME_BLOCK", block)
            ok("run", replay, "--out-dir", tmp / name, "--force")
            outs.append(tmp / name)
    finally:
        mp.undo()
    return outs


def test_the_log_is_what_this_file_tests(robot_runs) -> None:
    """Several blocks, irregular instants, sensors missing at most instants, a covariance per
    message, a truth of two of the four states."""
    mf = McapFile(robot_runs[0] / "sensors.mcap")
    dt = np.diff(mf.times())
    assert mf.steps() > 4 * 500 and np.ptp(dt) > 0.5 * dt.mean()
    z = mf.read_all(["/sensors/pose", "/sensors/odom"])
    assert np.isnan(z["/sensors/pose"][0][0]).any(axis=-1).mean() > 0.5
    covs = mf.message_covariances_of(["/sensors/pose"])["/sensors/pose"]
    have = np.isfinite(covs).all(axis=(-2, -1))
    assert have.sum() > 10 and np.ptp(covs[have][:, 0, 0]) > 0
    summary = json.loads((robot_runs[0] / "summary.json").read_text())
    assert summary["truth"]["states"] == ["px", "py"]


def test_blocked_estimates_equal_the_whole_replay(robot_runs) -> None:
    """Every architecture's means and covariances (FBS's backward pass across the blocks, the
    local filters' joint covariance of the rules that read it), and the measurement pattern."""
    whole, blocked = (McapFile(d / "estimates.mcap") for d in robot_runs)
    topics = [f"/estimates/{a}" for a in ARCHS]
    a, b = whole.read_all(topics), blocked.read_all(topics)
    for t in topics:
        np.testing.assert_allclose(b[t][0], a[t][0], rtol=RTOL, atol=1e-12, err_msg=t)
        np.testing.assert_allclose(b[t][1], a[t][1], rtol=RTOL, atol=1e-15, err_msg=t)
    pa, pb = (f.metadata["fusionlog.provenance"] for f in (whole, blocked))
    assert pb["measurement_pattern"] == pa["measurement_pattern"] != "complete"


def test_blocked_summary_equals_the_whole_replay(robot_runs) -> None:
    """Metrics over the truthed states, the exact values of the one-log route with its bound
    check, NIS per sensor with its whiteness: as from the whole log."""
    whole, blocked = (json.loads((d / "summary.json").read_text()) for d in robot_runs)
    _close(blocked, whole)
    for a in ARCHS:
        entry = whole["architectures"][a]
        assert entry["expected"]["mse"] is not None and "bound" in entry, a
        assert entry["mse_per_state"][1] is None and entry["mse_per_state"][0] > 0  # vx: none
        assert "nis" in entry


def test_blocked_recording_equals_the_whole_replay(robot_runs) -> None:
    a, b = (read_recording(d / "evaluation.rrd") for d in robot_runs)
    np.testing.assert_array_equal(a["steps"], b["steps"])
    assert a["series"].keys() == b["series"].keys()
    for key, v in a["series"].items():
        np.testing.assert_allclose(b["series"][key], v, rtol=RTOL, atol=1e-12, err_msg=key)


def _irregular_csv(folder: Path, rows: int) -> Path:
    """A CSV log of `rows` irregular instants (5 ms +- 40 %), two position sensors each missing
    at 10 % of them, a truth of the position alone, and its replay file."""
    rng = np.random.default_rng(34)
    t = np.cumsum(np.round(5e6 * (1 + 0.4 * rng.uniform(-1, 1, rows)))).astype(np.int64)
    v = 0.01 * np.cumsum(rng.normal(size=rows))
    p = 1.0 + np.cumsum(v) * 0.005
    a, b = p + rng.normal(size=rows), p + rng.normal(size=rows)
    a[rng.random(rows) < 0.1] = np.nan
    b[rng.random(rows) < 0.1] = np.nan
    lines = (f"{x},{y:.6f},{z:.6f},{q:.9f}" for x, y, z, q in zip(t, a, b, p, strict=True))
    (folder / "log.csv").write_text("time,a,b,p\n" + "\n".join(lines) + "\n")
    sensors = "".join(
        f'[[sensors]]\nname = "{x}"\nsource = "log.csv"\nvalues = ["{x}"]\ntime_unit = "ns"\n'
        "H = [[1.0, 0.0]]\nR = 1.0\n"
        for x in "ab"
    )
    replay = folder / "replay.toml"
    replay.write_text(
        '[scenario]\nname = "irregular"\nstate_names = ["p", "v"]\n'
        '[model]\nkind = "constant-velocity"\nn0 = 0.5\n'
        "[prior]\nmean = [1.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n" + sensors
        + '[truth]\nsource = "log.csv"\nvalues = ["p"]\nstates = ["p"]\n'
        'time_unit = "ns"\nmatch = "exact"\n'
        '[estimate]\narchitectures = ["CKF", "MSC-GMF", "HKF", "FBS"]\n'
    )  # fmt: skip
    return replay


def test_peak_memory_of_a_replay_does_not_grow_with_the_instants(tmp_path, monkeypatch) -> None:
    """The Python allocations' peak (tracemalloc: numpy's arrays included) of estimating and
    evaluating an imported irregular replay with missing readings and a partial truth, in
    blocks of 1000 instants, the recording decimated to 150 points per series: twice the
    instants, the same peak within 10 % (the whole log at once: +60 % here)."""
    import tracemalloc

    from fusionlog.core import decimate

    monkeypatch.setenv("FUSIONLOG_TIME_BLOCK", "1000")
    monkeypatch.setattr(decimate, "DECIMATE_ABOVE", 500)
    monkeypatch.setattr(decimate, "BUCKETS", 50)
    peaks = []
    for rows in (2_000, 10_000, 20_000):  # the first: what is imported on first use
        folder = tmp_path / str(rows)
        folder.mkdir()
        replay = _irregular_csv(folder, rows)
        ok("import", replay, "-o", folder / "s.mcap")
        tracemalloc.start()
        try:
            ok("estimate", folder / "s.mcap", "-o", folder / "e.mcap")
            ok("evaluate", folder / "s.mcap", folder / "e.mcap", "-o", folder / "ev.rrd",
               "--summary", folder / "summary.json")  # fmt: skip
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["architectures"]["FBS"]["expected"]["mse"] is not None
    assert peaks[2] <= 1.1 * peaks[1], peaks
