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
from long_helpers import (
    estimates_close,
    series_close,
    summaries,
    summaries_close,
    whole_and_blocked,
)

from fusionlog.io.mcap import McapFile

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
        ('state_names = ["x", "vx", "y", "vy"]',
         'state_names = ["px", "vx", "py", "vy"]'),
        ('source = "data/', f'source = "{data}/'),
        ('values = ["x [m]", "y [m]", "vx [m s^-1]", "vy [m s^-1]"]',
         'values = ["x [m]", "y [m]"]'),
        ('states = ["x", "y", "vx", "vy"]', 'states = ["px", "py"]'),
        ('architectures = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:mocap", "CI", "FBS"]',
         f"architectures = {json.dumps(ARCHS)}"),
    ):  # fmt: skip
        assert a in text, a
        text = text.replace(a, b)
    path = folder / "robot.toml"
    path.write_text(text)
    return path


def _close(a, b) -> None:
    summaries_close(a, b, rtol=RTOL, atol=1e-12, nan=True)


@pytest.fixture(scope="module")
def robot_runs(tmp_path_factory):
    """The replay run whole and in blocks of 500 instants."""
    tmp = tmp_path_factory.mktemp("long_replay")
    return whole_and_blocked(_robot_partial(tmp), tmp, 500)[:2]


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
    estimates_close(*robot_runs, ARCHS, mean=(RTOL, 1e-12), cov=(RTOL, 1e-15))
    whole, blocked = (McapFile(d / "estimates.mcap") for d in robot_runs)
    pa, pb = (f.metadata["fusionlog.provenance"] for f in (whole, blocked))
    assert pb["measurement_pattern"] == pa["measurement_pattern"] != "complete"


def test_blocked_summary_equals_the_whole_replay(robot_runs) -> None:
    """Metrics over the truthed states, the exact values of the one-log route with its bound
    check, NIS per sensor with its whiteness: as from the whole log."""
    whole, blocked = summaries(*robot_runs)
    _close(blocked, whole)
    for a in ARCHS:
        entry = whole["architectures"][a]
        assert entry["expected"]["mse"] is not None and "bound" in entry, a
        assert entry["mse_per_state"][1] is None and entry["mse_per_state"][0] > 0  # vx: none
        assert "nis" in entry


def test_blocked_recording_equals_the_whole_replay(robot_runs) -> None:
    series_close(*robot_runs, RTOL, 1e-12)


def _varying(rng, K1: int):
    """A random model (three sensors of sizes 1, 2, 1, the first two correlated) with its F,
    G Q G' drawn per interval (irregular instants), R scaled per instant (a covariance per
    message) and a quarter of the readings missing: the system and z (K1, m)."""
    import dataclasses

    from conftest import random_system

    from fusionlog.core.simulate import simulate

    system = random_system(np.random.default_rng(3), 3, [1, 2, 1], correlated=True)
    scale = 1 + 0.5 * rng.random(K1 - 1)
    Fs = np.eye(3) + (system.F - np.eye(3)) * scale[:, None, None]
    Qs = system.GQG * scale[:, None, None]
    Rs = system.R * (1 + rng.random(K1))[:, None, None]
    system = dataclasses.replace(system, Fs=Fs, Qs=Qs, Rs=Rs)
    _, z = simulate(system, K1 - 1, 4, 0, 1)
    z = z[0]
    z[rng.random(z.shape) < 0.25] = np.nan
    return system, z


def _blocked_peak(K1: int, block: int) -> int:
    """The peak of the Python allocations (tracemalloc) while a log of K1 instants (its system
    and readings made before) is estimated in blocks of time, FBS's backward pass and the
    exact analysis's included, each block's results dropped as a writer would."""
    import tracemalloc

    from fusionlog.core.architectures.replay_blocks import ReplayBlocks
    from fusionlog.core.exact_replay import replay_expected_blocks
    from fusionlog.driver.long_log import edges, replay_long_estimates, spool_readings
    from fusionlog.stages.evaluator.long_exact import LongReplayExact

    system, z = _varying(np.random.default_rng(K1), K1)
    archs = ["CKF", "HKF", "MSC-GMF", "CI", "SKF:s1", "FBS"]
    mask = ~np.isnan(z)
    tracemalloc.start()
    try:
        cut = ((k0, k1, {"z": (z[None, k0:k1],)}) for k0, k1 in edges(K1, block))
        spool = spool_readings(((k0, k1, {"z": d["z"][0]}) for k0, k1, d in cut), ["z"], z.shape[1])
        blocks = ReplayBlocks.of(system, archs, K1 - 1, block)
        for _k0, _k1, out in replay_long_estimates(blocks, spool, block):
            assert set(out) == set(archs)
        exact = replay_expected_blocks(system, system, archs, K1 - 1, block)
        long = LongReplayExact(exact, mask, system.m, block)
        for k0, k1 in edges(K1, block):
            assert set(long.window(k0, k1)) == set(archs)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_peak_memory_of_a_blocked_replay_does_not_grow_with_the_instants() -> None:
    """Blocks of 300 instants: twice the instants, the same peak within 10 % (the system's
    per-instant F, Q, R and the readings are the caller's, made before; the whole log at once
    keeps every instant's gains and covariances: its peak doubles)."""
    _blocked_peak(600, 300)  # what is imported on first use
    p1, p2 = _blocked_peak(3_000, 300), _blocked_peak(6_000, 300)
    assert p2 <= 1.1 * p1, (p1, p2)


def test_blocks_equal_the_whole_log_on_a_random_model() -> None:
    """Correlated sensors of different sizes, F, Q and R varying per instant, a quarter of the
    readings missing, blocks of 70 instants: every architecture's estimates (`replay_estimates`
    of the whole log) and exact values with the bound check (`replay_expected`) as whole."""
    from fusionlog.core.architectures import STATE_ARCHITECTURES
    from fusionlog.core.architectures.replay import replay_estimates
    from fusionlog.core.architectures.replay_blocks import ReplayBlocks
    from fusionlog.core.bound import bound_summary
    from fusionlog.core.exact_replay import replay_expected, replay_expected_blocks
    from fusionlog.driver.long_log import Spool, edges, replay_long_estimates
    from fusionlog.stages.evaluator.long_exact import LongReplayExact

    K1, B = 400, 70
    system, z = _varying(np.random.default_rng(5), K1)
    archs = [a for a in STATE_ARCHITECTURES if a != "SKF"] + ["SKF:s1", "SKF:s2", "SKF:s3"]
    whole = replay_estimates(system, archs, z[None])
    spool = Spool(z.shape[1])
    spool.write(0, z)
    blocks = ReplayBlocks.of(system, archs, K1 - 1, B)
    for k0, k1, out in replay_long_estimates(blocks, spool, B):
        for a in archs:
            w = whole[a]
            np.testing.assert_allclose(out[a].mean, w.mean[:, k0:k1], rtol=RTOL, atol=1e-12)
            np.testing.assert_allclose(out[a].cov, w.cov[k0:k1], rtol=RTOL, atol=1e-15)
    mask = ~np.isnan(z)
    exact = replay_expected(system, system, archs, mask, K1 - 1)
    long = LongReplayExact(replay_expected_blocks(system, system, archs, K1 - 1, B), mask, 4, B)
    for k0, k1 in edges(K1, B):
        for a, (ex, ratio) in long.window(k0, k1).items():
            for f in ("mse", "P", "nees", "dm"):
                got, want = getattr(ex, f), getattr(exact[a], f)[k0:k1]
                np.testing.assert_allclose(got, want, rtol=RTOL, atol=1e-15, err_msg=f"{a} {f}")
            np.testing.assert_allclose(ratio, exact[a].bound[k0:k1], rtol=RTOL)
    for a in archs:
        want = bound_summary(exact[a].bound)
        got = long.bound_summary(a)
        assert got["worst_step"] == want["worst_step"] and got["holds"] == want["holds"], a
        assert math.isclose(got["worst"], want["worst"], rel_tol=RTOL), a


def _sparse_file(path: Path, K1: int) -> None:
    """A one-run log of K1 instants k dt (regular: the layout records dt, not the times) whose
    truth has every instant and two sensors about 90 % and 60 % of them, at random: the layout
    record lists each sensor's steps (the `sparse` JSON)."""
    from fusionlog.io.mcap import McapWriter

    rng = np.random.default_rng(K1)
    at = {"/sensors/a": rng.random(K1) < 0.9, "/sensors/b": rng.random(K1) < 0.6}
    one = np.ones((1, 1))
    with open(path, "wb") as f, McapWriter(f, chunk_size=1 << 16) as w:  # (small blocks)
        for k in range(K1):
            w.write_values("/truth", k, k * 0.005, 0, one)
            for topic, mask in at.items():
                if mask[k]:
                    w.write_values(topic, k, k * 0.005, 0, one)


def _sparse_open_peak(path: Path, K1: int, block: int) -> int:
    """The peak of the Python allocations (tracemalloc) while the file's structure is learnt
    (the layout record parsed) and it is read in blocks of time, beyond the file's metadata
    text (read by the constructor) and its instants' times (one shared array, held here)."""
    import tracemalloc

    from fusionlog.core.timing import regular_times
    from fusionlog.io.mcap import McapFile

    times = regular_times(K1, 0.005)  # the array the layout's dt stands for, made before
    mf = McapFile(path)
    tracemalloc.start()
    try:
        got = 0
        for k0, k1, data in mf.iter_time_blocks(["/truth", "/sensors/a", "/sensors/b"], block):
            got += k1 - k0
            assert data["/sensors/a"].shape == (1, k1 - k0, 1)
        assert got == K1 and mf.times() is times
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_opening_a_sparse_log_does_not_grow_with_the_instants(tmp_path) -> None:
    """Four times the instants, the same peak within 10 % when a log whose sensors have
    readings at some instants is opened and read in blocks of 500 instants. The layout kept
    each sensor's steps as a Python list (a 36-byte int each, checked through a set) and each
    block of time read a (K+1,) mask: the peak grew ~110 bytes per instant here (1.3 MB at
    10^4 instants, 4.8 MB at 4*10^4); a sensor's steps are now one bit per instant, parsed a
    stretch of the record at a time."""
    small, large = tmp_path / "small.mcap", tmp_path / "large.mcap"
    _sparse_file(small, 10_000)
    _sparse_file(large, 40_000)
    _sparse_open_peak(small, 10_000, 500)  # what is imported on first use
    p1, p2 = _sparse_open_peak(small, 10_000, 500), _sparse_open_peak(large, 40_000, 500)
    assert p2 <= 1.1 * p1, (p1, p2)
