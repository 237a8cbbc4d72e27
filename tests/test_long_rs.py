"""Issue 34: a long log whose sensor carries its R in each message (DESIGN.md "MCAP files": a
`covariance` field dim x dim) is estimated and evaluated with its per-instant R (`System.Rs`)
read block of time by block, not held whole (8 m^2 bytes an instant).

References: the whole run of the same log (the whole-run path holds the (K+1, m, m) array:
blocked and whole compute the same recursions in the same order, so they agree to rounding,
1e-9 relative, as tests/test_long_replay.py argues), and the centralised KF written here from
its formulas (eqs. 14-18) with each message's own variance read from the JSON recording, the
constant-velocity model's F(Δ), Q(Δ) of eqs. (41)-(42) in closed form on the log's instants.

A simulated scenario cannot give a sensor a covariance per message (its `[[sensors]] R` is one
matrix); its sensors files take one when written by other tools, which `test_the_peak_...`
does with the project's writer.

The time-block size is the hidden setting FUSIONLOG_TIME_BLOCK (as tests/test_long_*.py).
"""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from long_helpers import time_block, whole_and_blocked
from test_long_replay import _close
from test_replay_sources import write_json_mcap

from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.topics import sensor_topic

ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:a", "CI", "FBS", "AVG"]
N0 = 0.5
T0 = 1_700_000_000  # s: the recording's clock
RTOL = 1e-9


def _recording(folder: Path, per_sensor: int, seed: int = 34) -> tuple[Path, dict]:
    """A replay of two position sensors at their own irregular instants: `a` in a JSON MCAP
    whose messages carry their own variance (0.05..5, the field `c`), `b` in a CSV with one R;
    the truth (p, v) at every instant in a CSV. Returns the replay file and a's data."""
    rng = np.random.default_rng(seed)
    ta = np.round(np.cumsum(rng.uniform(0.02, 0.06, per_sensor)), 4)
    tb = np.round(np.cumsum(rng.uniform(0.02, 0.06, per_sensor)) + 0.00005, 5)
    t = np.union1d(ta, tb)
    v = 1.0 + 0.2 * np.cumsum(rng.normal(size=len(t))) * 0.05
    p = np.concatenate([[0.0], np.cumsum(v[:-1] * np.diff(t))])
    ra = np.exp(rng.uniform(np.log(0.05), np.log(5.0), per_sensor))
    za = p[np.searchsorted(t, ta)] + np.sqrt(ra) * rng.normal(size=per_sensor)
    zb = p[np.searchsorted(t, tb)] + np.sqrt(0.5) * rng.normal(size=per_sensor)
    msgs = [
        (int((T0 + x) * 1e9), {"t": T0 + float(x), "z": float(z), "c": [float(r)]})
        for x, z, r in zip(ta, za, ra, strict=True)
    ]
    write_json_mcap(folder / "a.mcap", {"/a": msgs})
    (folder / "b.csv").write_text(
        "time,b\n" + "".join(f"{T0 + x:.5f},{float(z)!r}\n" for x, z in zip(tb, zb, strict=True))
    )
    rows = zip(t, p, v, strict=True)
    (folder / "truth.csv").write_text(
        "time,p,v\n" + "".join(f"{T0 + x:.5f},{float(a)!r},{float(b)!r}\n" for x, a, b in rows)
    )
    replay = folder / "replay.toml"
    replay.write_text(
        '[scenario]\nname = "long_rs"\nstate_names = ["p", "v"]\n'
        f'[model]\nkind = "constant-velocity"\nn0 = {N0}\n'
        "[prior]\nmean = [0.0, 1.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
        '[[sensors]]\nname = "a"\nsource = "a.mcap"\ntopic = "/a"\nvalues = ["z"]\n'
        'time = "t"\ncovariance = "c"\nH = [[1.0, 0.0]]\nR = 1.0\n'
        '[[sensors]]\nname = "b"\nsource = "b.csv"\nvalues = ["b"]\nH = [[1.0, 0.0]]\n'
        "R = 0.5\n"
        '[truth]\nsource = "truth.csv"\nvalues = ["p", "v"]\nstates = ["p", "v"]\n'
        'match = "exact"\n'
        f"[estimate]\narchitectures = {json.dumps(ARCHS)}\n"
    )  # fmt: skip
    return replay, {"t": ta, "z": za, "r": ra}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The replay of 2 x 700 readings run whole and in blocks of 230 instants (7 blocks)."""
    tmp = tmp_path_factory.mktemp("long_rs")
    replay, a = _recording(tmp, 700)
    whole, blocked, _ = whole_and_blocked(replay, tmp, 230)
    return {"whole": whole, "blocked": blocked}, a


def _estimates(folder: Path) -> dict:
    mf = McapFile(folder / "estimates.mcap")
    return {t: mf.read_all([t])[t] for t in mf.topics if t.startswith("/estimates/")}


def test_the_log_spans_several_blocks_with_a_covariance_per_message(runs) -> None:
    out, a = runs
    mf = McapFile(out["whole"] / "sensors.mcap")
    assert mf.steps() == 1400 and mf.steps() > 5 * 230
    got = mf.message_covariances(sensor_topic("a"))
    have = np.isfinite(got[:, 0, 0])
    np.testing.assert_array_equal(got[have, 0, 0], a["r"])  # as recorded, message by message


def test_blocked_estimates_and_summary_equal_the_whole_run(runs) -> None:
    out, _ = runs
    whole, blocked = _estimates(out["whole"]), _estimates(out["blocked"])
    assert whole.keys() == blocked.keys() and len(whole) == len(ARCHS)
    for topic, (mean, cov) in whole.items():
        np.testing.assert_allclose(blocked[topic][0], mean, rtol=RTOL, atol=1e-12, err_msg=topic)
        np.testing.assert_allclose(blocked[topic][1], cov, rtol=RTOL, atol=1e-15, err_msg=topic)
    a = json.loads((out["whole"] / "summary.json").read_text())
    b = json.loads((out["blocked"] / "summary.json").read_text())
    for s in (a, b):  # what differs by construction: where and how it ran
        s.pop("provenance", None)
        s.pop("timing", None)
    _close(a, b)
    assert a["architectures"]["CKF"]["expected"]["mse"] is not None


def test_ckf_is_the_kalman_filter_with_each_messages_variance(runs) -> None:
    """The blocked CKF against eqs. (14)-(18) written here: a's variance at each of its
    instants from the JSON recording, b's R = 0.5, F(Δ), Q(Δ) of the constant velocity."""
    out, a = runs
    mf = McapFile(out["blocked"] / "sensors.mcap")
    t = np.asarray(mf.times())
    za, zb = (mf.read_all([sensor_topic(s)])[sensor_topic(s)][0, :, 0] for s in "ab")
    r = np.full(len(t), np.nan)
    r[np.isfinite(za)] = a["r"]
    x, P = np.array([0.0, 1.0]), np.eye(2)
    H = np.array([[1.0, 0.0]])
    means, covs = [], []
    for k in range(len(t)):
        if k:
            d = t[k] - t[k - 1]
            F = np.array([[1.0, d], [0.0, 1.0]])
            Q = N0 * np.array([[d**3 / 3, d**2 / 2], [d**2 / 2, d]])
            x, P = F @ x, F @ P @ F.T + Q
        for z, R in ((za[k], r[k]), (zb[k], 0.5)):
            if np.isfinite(z):
                S = H @ P @ H.T + R
                K = P @ H.T / S
                x = x + (K * (z - H @ x)).ravel()
                IKH = np.eye(2) - K @ H
                P = IKH @ P @ IKH.T + R * K @ K.T
        means.append(x)
        covs.append(P)
    mean, cov = _estimates(out["blocked"])["/estimates/CKF"]
    # the KF is contractive: rounding does not grow along the log (1e-9 of the values)
    np.testing.assert_allclose(mean[0], means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov, covs, rtol=1e-9, atol=1e-12)


# -- memory ---------------------------------------------------------------------------------


def _sensors_file(path: Path, K1: int, seed: int = 7) -> None:
    """A one-run sensors file of K1 instants (dt 1 s): the truth, sensor s1 with a variance
    of its own in each message's covariance field (its readings drawn with it), s2 with its R."""
    from fusionlog.io.mcap import VALUES, McapWriter
    from fusionlog.io.mcap.run_steps import RunColumn

    rng = np.random.default_rng(seed)
    t = np.arange(K1) * 1.0
    x = np.stack([np.cumsum(rng.normal(size=K1)) * 0.01, rng.normal(size=K1)], axis=1)
    r = np.exp(rng.uniform(-1, 1, K1))
    z1 = x[:, :1] + np.sqrt(r)[:, None] * rng.normal(size=(K1, 1))
    z2 = x[:, :1] + rng.normal(size=(K1, 1))
    with open(path, "wb") as f, McapWriter(f) as w:
        w.write_run_steps(0, t, [
            RunColumn("/truth", VALUES, x),
            RunColumn("/sensors/s1", VALUES, z1, r[:, None, None]),
            RunColumn("/sensors/s2", VALUES, z2),
        ])  # fmt: skip


def _peak(path: Path, block: int) -> int:
    """tracemalloc's peak while the log's per-instant R is read (`with_message_covariances` of
    a log taken in blocks of time) and every architecture estimates it block by block, FBS's
    backward pass and the exact analysis included, each block's results dropped as a writer
    does. The file's instants and readings' pattern are the caller's, made before."""
    from fusionlog.core.architectures.replay_blocks import ReplayBlocks
    from fusionlog.core.exact_replay import replay_expected_blocks
    from fusionlog.core.model import ajgl2009
    from fusionlog.driver.long_log import edges, replay_long_estimates, spool_readings
    from fusionlog.stages.evaluator.long_exact import LongReplayExact
    from fusionlog.stages.noise import with_message_covariances

    mf = McapFile(path)
    times, K1 = mf.times(), mf.steps()
    system = ajgl2009(1.0, 2)
    mask = np.ones((K1, 2), bool)
    topics = ["/sensors/s1", "/sensors/s2"]
    archs = ["CKF", "HKF", "MSC-GMF", "CI", "SKF:s1", "FBS"]
    tracemalloc.start()
    try:
        sy = with_message_covariances(system.on_times(times), mf, blocked=True)
        assert sy.Rs is not None and len(sy.Rs) == K1
        spool = spool_readings(mf.iter_time_blocks(topics, block), topics, 2)
        blocks = ReplayBlocks.of(sy, archs, K1 - 1, block)
        for _k0, _k1, got in replay_long_estimates(blocks, spool, block):
            assert set(got) == set(archs)
        spool.close()
        long = LongReplayExact(replay_expected_blocks(sy, sy, archs, K1 - 1, block), mask, 2, block)
        for k0, k1 in edges(K1, block):
            assert set(long.window(k0, k1)) == set(archs)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.memory
def test_the_peak_does_not_grow_with_the_log(tmp_path, monkeypatch) -> None:
    """Four times the instants (blocks of 500), the peak grows by less than 8 bytes per added
    instant; the stacked R held whole is 8 m^2 = 32 bytes an instant here (and the messages'
    covariances read whole 8 more), and the whole log's gains and covariances far more. (Both
    logs span several of the file's chunks, whose decoding sets the reading's peak.)"""
    time_block(monkeypatch, 500)
    small, large = tmp_path / "small.mcap", tmp_path / "large.mcap"
    K = 20_000
    _sensors_file(small, K)
    _sensors_file(large, 4 * K)
    _peak(small, 500)  # what is imported on first use
    p1, p2 = _peak(small, 500), _peak(large, 500)
    assert p2 - p1 < 8 * 3 * K, (p1, p2)


def test_blocked_R_is_the_whole_logs(tmp_path, monkeypatch) -> None:
    """The per-instant R formed per block (every instant, a stretch, a sensor's subset) is the
    whole array's bit for bit; s2's messages carry none: its R at every instant."""
    from fusionlog.core.model import ajgl2009
    from fusionlog.stages.noise import with_message_covariances

    time_block(monkeypatch, 300)
    path = tmp_path / "log.mcap"
    _sensors_file(path, 2_000)
    mf = McapFile(path)
    system = ajgl2009(1.0, 2).on_times(mf.times())
    whole = with_message_covariances(system, mf).Rs
    blocked = with_message_covariances(system, McapFile(path), blocked=True).Rs
    assert isinstance(whole, np.ndarray) and not isinstance(blocked, np.ndarray)
    np.testing.assert_array_equal(np.asarray(blocked), whole)
    for k in (0, 299, 300, 1999):
        np.testing.assert_array_equal(blocked[k], whole[k])
    np.testing.assert_array_equal(blocked[250:1250], whole[250:1250])
    np.testing.assert_array_equal(blocked[:, 1:][:, :, 1:][700:900], whole[700:900, 1:, 1:])
    assert (whole[:, 1, 1] == 1.0).all() and (whole[:, 0, 1] == 0.0).all()
    r = mf.read_all(["/sensors/s1"])  # (the readings: the variances are the messages')
    assert r["/sensors/s1"].shape == (1, 2000, 1)
    assert len(np.unique(whole[:, 0, 0])) == 2000


# -- a nonlinear late log's drawn arrivals ------------------------------------------------------


def test_nonlinear_drawn_arrivals_are_read_per_block(tmp_path, monkeypatch) -> None:
    """The EKF radar log with radar2's delays drawn per reading (0.5..2.5 s) and the camera
    3 s late, estimated in blocks of 45 instants without the whole run's arrivals (the reader
    of the whole run's fails here): the same estimates, bit for bit, as the whole run."""
    from test_long_late_more import RADAR

    import fusionlog.io.mcap.arrival as arrival

    sc = tmp_path / "late.toml"
    sc.write_text(
        RADAR.format(
            steps=150, archs='["CKF", "MSC"]', late="reprocess", latency="{min = 0.5, max = 2.5}"
        )
    )
    ok("simulate", sc, "-o", tmp_path / "s.mcap")
    time_block(monkeypatch, None)
    ok("estimate", tmp_path / "s.mcap", "-o", tmp_path / "whole.mcap")

    def whole(*a, **kw):
        raise AssertionError("the whole run's arrivals read")

    monkeypatch.setattr(arrival, "read_arrivals", whole)
    time_block(monkeypatch, 45)
    ok("estimate", tmp_path / "s.mcap", "-o", tmp_path / "blocked.mcap")
    a, b = (McapFile(tmp_path / f"{n}.mcap") for n in ("whole", "blocked"))
    for topic in ("/estimates/CKF", "/estimates/MSC"):
        (ma, ca), (mb, cb) = a.read_all([topic])[topic], b.read_all([topic])[topic]
        np.testing.assert_array_equal(mb, ma, err_msg=topic)
        np.testing.assert_array_equal(cb, ca, err_msg=topic)
