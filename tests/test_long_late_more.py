"""Issue 34, continued: what took the whole run of a long one-run log with late sensors --
retrodiction with the rules that read the locals' joint covariance (MSC-GMF, AVG), and
nonlinear (EKF/UKF) late sensors -- in blocks of time.

Blocks of a few dozen instants (the hidden setting FUSIONLOG_TIME_BLOCK), so a reading taken
before a block edge arrives after it and what crosses the edge must be carried: for
retrodiction the plans' state (Al1's stored estimates, the readings not yet arrived) and J's
plan-time recursion, which past the latency window repeats bit for bit, so the short plans'
steady maps stand for the log (`core.latency_long`); for the EKF/UKF lanes the states a
reprocess rewinds to, the estimates Al1 retrodicts from, the last W instants' readings and
neglect's newest measurement times (`core.nonlinear.late_feed`). The same log taken whole is
the reference: its filters are checked against filters written from the formulas in
tests/test_retrodict_t2t.py and tests/test_latency_nonlinear.py.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from test_long_late import EXACT_ATOL, JOINT, RTOL, _close, _scenario, _Spy

from fusionlog.io.mcap import McapFile
from fusionlog.io.rrd import read_recording
from fusionlog.stages.evaluator.long_evaluator import LongEvaluator


def _run(scenario: Path, out: Path, block: int | None, mp: pytest.MonkeyPatch) -> Path:
    if block is None:
        mp.delenv("FUSIONLOG_TIME_BLOCK", raising=False)
    else:
        mp.setenv("FUSIONLOG_TIME_BLOCK", str(block))
    ok("run", scenario, "--out-dir", out, "--force")
    return out


# --- retrodiction with MSC-GMF and AVG ---------------------------------------------------


@pytest.fixture(
    scope="module",
    params=["plans of the whole log", "steady plans of 512"],
)
def retro_runs(tmp_path_factory, request):
    """test_long_late's log (s2 1 s late, s3 3 s, 1200 instants) retrodicted by MSC-GMF and
    AVG, taken whole and in blocks of 50: with late plans over all of it, and with late plans
    of 512 instants standing for it (their steady middle repeated)."""
    import fusionlog.core.architectures.long_log as long_log

    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp("retro-joint")
    sc = _scenario(tmp, "retrodict", JOINT)
    try:
        whole = _run(sc, tmp / "whole", None, mp)
        if request.param != "plans of the whole log":
            mp.setattr(long_log, "HORIZONS", (512,))
        spy = _Spy(mp)
        blocked = _run(sc, tmp / "blocked", 50, mp)
    finally:
        mp.undo()
    return request.param != "plans of the whole log", whole, blocked, spy


def test_retrodiction_with_j_goes_in_blocks(retro_runs) -> None:
    """Both stages took the log's 24 blocks of time (not the whole run at once)."""
    spy = retro_runs[-1]
    assert (spy.estimated, spy.evaluated) == (24, 24)


def test_retrodiction_with_j_estimates_equal_the_whole_log(retro_runs) -> None:
    """MSC-GMF's and AVG's means (to rounding: test_long_late.RTOL) and covariances (the same
    maps: to the bit) across edges that late readings cross."""
    _, whole, blocked, _ = retro_runs
    topics = [f"/estimates/{a}" for a in JOINT]
    a = McapFile(whole / "estimates.mcap").read_all(topics)
    b = McapFile(blocked / "estimates.mcap").read_all(topics)
    for t in topics:
        scale = np.abs(a[t][0]).max()
        np.testing.assert_allclose(b[t][0], a[t][0], rtol=0, atol=RTOL * scale, err_msg=t)
        np.testing.assert_array_equal(b[t][1], a[t][1], err_msg=t)


def test_retrodiction_with_j_summary_equals_the_whole_log(retro_runs) -> None:
    """The Monte Carlo metrics, the exact values and the bound check as from the whole log
    (short plans: the exact values within the whole log's own rounding, `EXACT_ATOL`); the
    bound holds (the rules fuse with the true J)."""
    steady, whole, blocked, _ = retro_runs
    a, b = (json.loads((d / "summary.json").read_text()) for d in (whole, blocked))
    _close(b, a, steady=steady)
    assert b["late"] == "retrodict"
    for arch in JOINT:
        got = b["architectures"][arch]
        assert got["expected"]["mse"] is not None and got["bound"]["holds"], arch


def test_retrodiction_with_j_recording_equals_the_whole_log(retro_runs) -> None:
    """The recording's series (test_long_late's tolerances)."""
    steady, whole, blocked, _ = retro_runs
    atol = 2 * 5 * RTOL * (100 + 1199)
    a, b = (read_recording(d / "evaluation.rrd") for d in (whole, blocked))
    np.testing.assert_array_equal(a["steps"], b["steps"])
    assert a["series"].keys() == b["series"].keys()
    for key, v in a["series"].items():
        tol = EXACT_ATOL if steady and ("expected" in key or "bound" in key) else atol
        np.testing.assert_allclose(b["series"][key], v, rtol=1e-9, atol=tol, err_msg=key)


# --- nonlinear late sensors ----------------------------------------------------------------

RADAR = """
[scenario]
name = "radar_late"
steps = {steps}
runs = 1
seed = 2026
dt = 1.0
[model]
kind = "constant-velocity"
axes = 2
n0 = 0.5
[prior]
mean = [2000.0, 10.0, 3000.0, -5.0]
cov = [[400.0, 0.0, 0.0, 0.0], [0.0, 25.0, 0.0, 0.0], [0.0, 0.0, 400.0, 0.0], [0.0, 0.0, 0.0, 25.0]]
[[sensors]]
name = "radar1"
kind = "range-bearing"
position = [0.0, 0.0]
R = [[100.0, 0.0], [0.0, 3.0e-4]]
[[sensors]]
name = "radar2"
kind = "range-bearing"
position = [5000.0, 0.0]
R = [[100.0, 0.0], [0.0, 3.0e-4]]
latency = {latency}
[[sensors]]
name = "camera"
kind = "bearing"
position = [3000.0, 4000.0]
R = 3.0e-4
period = 2.0
latency = 3.0
[estimate]
filter = "EKF"
architectures = {archs}
late = "{late}"
"""

TURN = """
[scenario]
name = "turn_late"
steps = {steps}
runs = 1
seed = 7
dt = 1.0
[model]
kind = "coordinated-turn"
q = [0.05, 0.05]
q_turn = 1.0e-5
[prior]
mean = [0.0, 15.0, 500.0, 0.0, 0.05]
cov = [[100.0, 0.0, 0.0, 0.0, 0.0], [0.0, 16.0, 0.0, 0.0, 0.0], [0.0, 0.0, 100.0, 0.0, 0.0],
       [0.0, 0.0, 0.0, 16.0, 0.0], [0.0, 0.0, 0.0, 0.0, 4.0e-4]]
[[sensors]]
name = "radar"
kind = "range-bearing"
position = [0.0, 0.0]
R = [[25.0, 0.0], [0.0, 1.0e-3]]
latency = {latency}
[[sensors]]
name = "camera"
kind = "bearing"
position = [600.0, 800.0]
R = 3.0e-4
period = 2.0
latency = 3.0
[estimate]
filter = "UKF"
architectures = {archs}
late = "{late}"
"""

#: Every architecture the lanes take with late sensors (FBS refused: a smoother); retrodict
#: with EKF locals refuses the rules that read J (`late_policy.ekf_retrodict_refusal`), and
#: the UKF retrodicts not at all (`late_policy.nonlinear_refusal`).
ALL = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF:camera", "CI", "AVG"]
NO_J = [a for a in ALL if a not in JOINT]
NONLINEAR = [
    ("EKF", "reprocess", "1.0", ALL),
    ("EKF", "neglect", "1.0", ALL),
    ("EKF", "retrodict", "1.0", NO_J),
    ("EKF", "reprocess", "{min = 0.5, max = 2.5}", ["CKF", "MSC"]),  # random delays
    ("UKF", "reprocess", "0.0", ALL),
    ("UKF", "neglect", "2.0", ALL),
]
STEPS = 150
BLOCK = 45  # edges at 45, 90, 135: neither the camera's period nor a lag divides them


@pytest.fixture(scope="module", params=NONLINEAR, ids=lambda p: f"{p[0]} {p[1]} {p[2]}")
def nonlinear_runs(tmp_path_factory, request):
    """A nonlinear log of 151 instants whose sensors arrive late (the camera 3 s, every other
    instant; a radar by the parameter), whole and in blocks of 45."""
    import fusionlog.core.nonlinear.long_log as nl_long

    filt, late, latency, archs = request.param
    text = (RADAR if filt == "EKF" else TURN).format(
        steps=STEPS, archs=json.dumps(archs), late=late, latency=latency
    )
    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp("nonlinear-late")
    sc = tmp / "late.toml"
    sc.write_text(text)
    spied = {"estimated": 0, "evaluated": 0}
    try:
        whole = _run(sc, tmp / "whole", None, mp)
        inner, add = nl_long.estimate_blocks, LongEvaluator.add

        def estimate_blocks(*a, **kw):
            for got in inner(*a, **kw):
                spied["estimated"] += 1
                yield got

        def evaluated(ev, *a, **kw):
            spied["evaluated"] += 1
            return add(ev, *a, **kw)

        mp.setattr(nl_long, "estimate_blocks", estimate_blocks)
        mp.setattr(LongEvaluator, "add", evaluated)
        blocked = _run(sc, tmp / "blocked", BLOCK, mp)
    finally:
        mp.undo()
    return archs, whole, blocked, spied


def test_nonlinear_late_log_goes_in_blocks(nonlinear_runs) -> None:
    """Both stages took the log's 4 blocks of time (not the whole run at once)."""
    assert nonlinear_runs[-1] == {"estimated": 4, "evaluated": 4}


def test_nonlinear_late_estimates_equal_the_whole_run(nonlinear_runs) -> None:
    """Every architecture's means and covariances: the same filter operations on the same
    readings in the same order (the rewinds, Al1 and neglect's drops included), so equal to
    rounding (1e-12 of the largest mean, far above it: the blocks cut no sum)."""
    archs, whole, blocked, _ = nonlinear_runs
    topics = [f"/estimates/{a}" for a in archs]
    a = McapFile(whole / "estimates.mcap").read_all(topics)
    b = McapFile(blocked / "estimates.mcap").read_all(topics)
    for t in topics:
        scale = np.abs(a[t][0]).max()
        np.testing.assert_allclose(b[t][0], a[t][0], rtol=0, atol=1e-12 * scale, err_msg=t)
        cs = np.abs(a[t][1]).max()
        np.testing.assert_allclose(b[t][1], a[t][1], rtol=0, atol=1e-12 * cs, err_msg=t)


def _near(a, b, path=""):
    """Sums over 151 instants in another order: 1e-12 relative."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _near(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _near(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        if math.isnan(a):
            assert math.isnan(b), path
        else:
            assert math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-15), (path, a, b)
    else:
        assert a == b, (path, a, b)


def test_nonlinear_late_summary_and_recording_equal_the_whole_run(nonlinear_runs) -> None:
    """The Monte Carlo metrics, the PCRB, APE/RPE, the policy, and the recording's series."""
    archs, whole, blocked, _ = nonlinear_runs
    a, b = (json.loads((d / "summary.json").read_text()) for d in (whole, blocked))
    _near(b, a)
    assert b["late"] == a["late"] and b["pcrb"] is not None
    assert list(b["architectures"]) == archs
    x, y = (read_recording(d / "evaluation.rrd") for d in (whole, blocked))
    np.testing.assert_array_equal(x["steps"], y["steps"])
    assert x["series"].keys() == y["series"].keys()
    for key, v in x["series"].items():
        np.testing.assert_allclose(y["series"][key], v, rtol=1e-9, atol=1e-9, err_msg=key)


# --- memory --------------------------------------------------------------------------------


def _peaks(tmp_path, monkeypatch, path: Path, archs, sizes, block: int) -> list[int]:
    """The Python allocations' peak (tracemalloc) of a whole `run` of each size in blocks of
    `block` instants, a recording decimated to 20 buckets per series."""
    import tracemalloc

    from fusionlog.core import decimate
    from fusionlog.scenario import load_scenario
    from fusionlog.stages.run import run_pipeline

    monkeypatch.setenv("FUSIONLOG_TIME_BLOCK", str(block))
    monkeypatch.setattr(decimate, "DECIMATE_ABOVE", 100)
    monkeypatch.setattr(decimate, "BUCKETS", 20)
    peaks = []
    for K in sizes:  # the first: what is imported on first use
        sc = load_scenario(path, steps=K)
        tracemalloc.start()
        try:
            run_pipeline(sc, tmp_path / str(K), archs=archs, force=True)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    return peaks


def test_peak_memory_of_retrodiction_with_j_does_not_grow(tmp_path, monkeypatch) -> None:
    """MSC-GMF and AVG retrodicting in blocks of 1000 instants, late plans of 512 standing for
    the log: twice the instants, the same peak within 10 % (the whole run holds its plans'
    maps, estimates and per-instant sums: ~2 kB per instant)."""
    import fusionlog.core.architectures.long_log as long_log

    monkeypatch.setattr(long_log, "HORIZONS", (512,))
    spy = _Spy(monkeypatch)
    path = _scenario(tmp_path, "retrodict", JOINT)
    peaks = _peaks(tmp_path, monkeypatch, path, JOINT, (2_000, 10_000, 20_000), 1000)
    assert spy.estimated == spy.evaluated == 3 + 11 + 21  # every log in blocks
    assert peaks[2] <= 1.1 * peaks[1], peaks


def test_peak_memory_of_a_nonlinear_late_log_does_not_grow(tmp_path, monkeypatch) -> None:
    """The EKF radar log reprocessing its late readings (CKF, radar2 1 s and the camera 3 s
    late) in blocks of 60 instants: twice the instants, the same peak within 10 %. Measured:
    1.79 MB at 500 instants, 1.89 MB at 1000 -- ~190 bytes an instant still held somewhere
    (not yet traced: the on-time log's test bounds its growth below 100 bytes an instant)."""
    path = tmp_path / "late.toml"
    path.write_text(RADAR.format(steps=10, archs='["CKF"]', late="reprocess", latency="1.0"))
    peaks = _peaks(tmp_path, monkeypatch, path, ["CKF"], (200, 500, 1000), 60)
    assert peaks[2] <= 1.1 * peaks[1], peaks
