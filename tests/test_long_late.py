"""Issues 30 and 34: a long one-run log whose sensors arrive late, in blocks of time.

Two sensors late by fixed latencies of 3 and 1 instants (dt = 1 s), a third on time; blocks of
50 instants (the hidden setting FUSIONLOG_TIME_BLOCK), so a reading taken before a block edge
arrives after it and what crosses the edge (the stacked window a reprocess rewinds over, the
estimates Al1 retrodicts from, the readings not yet arrived) must be carried. The same log
taken whole is the reference: its late plans are checked against filters written from the
formulas in tests/test_latency.py and test_retrodict_t2t.py. Blocked and whole run the same
maps (the covariances to the bit); the means differ only by where the recursion is cut (the
order of roundings), the summary's sums by the order of their terms.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok

import fusionlog.driver.long_log as driver_long_log
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.arrival import read_arrivals
from fusionlog.io.rrd import read_recording
from fusionlog.stages.evaluator.long_evaluator import LongEvaluator

SCENARIO = """
[scenario]
name = "long_late"
steps = {steps}
runs = 1
seed = 34
dt = 1.0
state_names = ["position", "velocity"]
[model]
kind = "constant-velocity"
n0 = 0.16
[prior]
mean = [100.0, -1.0]
cov = [[1.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "s1"
H = [[1.0, 0.0]]
R = 1.0
[[sensors]]
name = "s2"
H = [[1.0, 0.0]]
R = 2.0
latency = 1.0
[[sensors]]
name = "s3"
H = [[1.0, 0.0]]
R = 0.5
latency = 3.0
[estimate]
architectures = {archs}
late = "{late}"
"""

#: The paper's architectures with late sensors (FBS: a latency has no meaning for a
#: fixed-interval smoother, refused) and the other rules. Retrodiction with MSC-GMF and AVG
#: stays whole on a long log (`core.latency_long`): `test_retrodiction_with_j_is_whole`.
ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "SKF:s3", "CI", "AVG", "ICI", "EI"]
JOINT = ["MSC-GMF", "AVG"]


def archs_of(late: str, archs=ARCHS) -> list[str]:
    return [a for a in archs if late != "retrodict" or a not in JOINT]


POLICIES = ["reprocess", "neglect", "retrodict"]
STEPS = 1199
#: HKF's plans reach their steady map after ~1600 instants here (its information-form
#: recursion wanders at 1e-14 before it repeats), so the short plans of 512 leave it out
STEADY_ARCHS = [a for a in ARCHS if a != "HKF"]

# Means grow to ~|100 - 2000| (velocity -1): blocking reorders roundings of O(1e-16) relative
# in a contractive recursion, so 1e-12 of the largest mean; a summary's sums over 2000 terms in
# another order: 1e-12 relative.
RTOL = 1e-12


def _scenario(tmp: Path, late: str, archs: list[str], steps: int = STEPS) -> Path:
    path = tmp / f"{late}.toml"
    path.write_text(SCENARIO.format(steps=steps, archs=json.dumps(archs), late=late))
    return path


class _Spy:
    """Counts the blocks of time the estimate and evaluate stages took (the blocked path)."""

    def __init__(self, mp: pytest.MonkeyPatch) -> None:
        self.estimated, self.evaluated = 0, 0
        inner, add = driver_long_log.long_estimates, LongEvaluator.add

        def long_estimates(*a, **kw):
            for got in inner(*a, **kw):
                self.estimated += 1
                yield got

        def evaluated(ev, *a, **kw):
            self.evaluated += 1
            return add(ev, *a, **kw)

        mp.setattr(driver_long_log, "long_estimates", long_estimates)
        mp.setattr(LongEvaluator, "add", evaluated)


def _run(scenario: Path, out: Path, block: int | None, mp: pytest.MonkeyPatch, *extra) -> Path:
    if block is None:
        mp.delenv("FUSIONLOG_TIME_BLOCK", raising=False)
    else:
        mp.setenv("FUSIONLOG_TIME_BLOCK", str(block))
    ok("run", scenario, "--out-dir", out, "--force", *extra)
    return out


@pytest.fixture(
    scope="module",
    params=[(p, v) for p in POLICIES for v in ("plans of the whole log", "steady plans of 512")],
    ids=lambda p: f"{p[0]}, {p[1]}",
)
def late_runs(tmp_path_factory, request):
    """One policy's log of 1200 instants taken whole and in blocks of 50: with late plans over
    all of it, and with late plans of 512 instants standing for it (their steady middle
    repeated, what a log longer than the horizons takes)."""
    import fusionlog.core.architectures.long_log as long_log

    late, variant = request.param
    archs = archs_of(late, ARCHS if variant == "plans of the whole log" else STEADY_ARCHS)
    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp(f"late-{late}")
    sc = _scenario(tmp, late, archs)
    try:
        whole = _run(sc, tmp / "whole", None, mp)
        if variant != "plans of the whole log":
            mp.setattr(long_log, "HORIZONS", (512,))
        spy = _Spy(mp)
        blocked = _run(sc, tmp / "blocked", 50, mp)
    finally:
        mp.undo()
    return late, archs, whole, blocked, spy


def test_the_blocked_log_went_in_blocks(late_runs) -> None:
    """Both stages took the log's 24 blocks of time (not the whole run at once)."""
    spy = late_runs[-1]
    assert (spy.estimated, spy.evaluated) == (24, 24)


def test_blocked_estimates_equal_the_whole_log(late_runs) -> None:
    """Every architecture's means (to rounding) and covariances (to the bit), across edges
    that late readings cross."""
    _, archs, whole, blocked, _ = late_runs
    topics = [f"/estimates/{a}" for a in archs]
    a = McapFile(whole / "estimates.mcap").read_all(topics)
    b = McapFile(blocked / "estimates.mcap").read_all(topics)
    for t in topics:
        scale = np.abs(a[t][0]).max()
        np.testing.assert_allclose(b[t][0], a[t][0], rtol=0, atol=RTOL * scale, err_msg=t)
        np.testing.assert_array_equal(b[t][1], a[t][1], err_msg=t)
    prov = McapFile(blocked / "estimates.mcap").metadata["fusionlog.provenance"]
    assert prov["measurement_pattern"] == "complete"


#: The exact analysis of late plans propagates the joint moments of the truth x_k and the
#: plan's state (`wrap`'s D = 0: no error form), so its values are differences of numbers of
#: the size of the truth's variance, var(position_k) ~ q k^3 / 3 (constant velocity, q = 0.16):
#: a few tens of roundings of that, absolute, at the log's end (the whole log's analysis) --
#: the short plans' analysis stops at the horizon's middle, where it is converged and smaller.
EXACT_ATOL = 32 * np.finfo(float).eps * 0.16 * STEPS**3 / 3


def _close(a, b, steady: bool, path=""):
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            if steady and k == "worst_step":  # argmax over ratios equal to roundings
                continue
            _close(a[k], b[k], steady, f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, steady, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        exact = steady and (".expected." in path or ".bound." in path)
        atol = EXACT_ATOL if exact else 1e-15
        assert math.isclose(a, b, rel_tol=RTOL, abs_tol=atol), (path, a, b)
    else:
        assert a == b, (path, a, b)


def test_blocked_summary_equals_the_whole_log(late_runs) -> None:
    """Monte Carlo metrics, the exact values (the late plans' analysis at each block's
    instants), the bound check and the policy, as from the whole log; with short plans standing
    for it, the exact values within the whole log's own rounding (`EXACT_ATOL`)."""
    late, archs, whole, blocked, _ = late_runs
    a, b = (json.loads((d / "summary.json").read_text()) for d in (whole, blocked))
    _close(b, a, steady=archs != archs_of(late))  # the short plans
    assert b["late"] == late
    for arch in archs:
        assert b["architectures"][arch]["expected"]["mse"] is not None
        assert "bound" in b["architectures"][arch]


def test_blocked_recording_equals_the_whole_log(late_runs) -> None:
    """The series drawn: each instant's squared error e^2 (|e| a few sigma, < 5 here) moves by
    2 |e| delta with the means' delta <= RTOL * max |mean| (max |mean| < 100 + STEPS); the
    exact series with short plans standing for the log as the summary's."""
    late, archs, whole, blocked, _ = late_runs
    steady = archs != archs_of(late)
    atol = 2 * 5 * RTOL * (100 + STEPS)
    a, b = (read_recording(d / "evaluation.rrd") for d in (whole, blocked))
    np.testing.assert_array_equal(a["steps"], b["steps"])
    assert a["series"].keys() == b["series"].keys()
    for key, v in a["series"].items():
        exact = steady and ("expected" in key or "bound" in key)
        tol = EXACT_ATOL if exact else atol
        np.testing.assert_allclose(b["series"][key], v, rtol=1e-9, atol=tol, err_msg=key)


def test_the_sensors_log_is_the_whole_runs(late_runs) -> None:
    """The simulation drawn in blocks writes the whole run's file: the readings and each late
    reading's arrival (its time plus its sensor's latency)."""
    _, _, whole, blocked, _ = late_runs
    assert (blocked / "sensors.mcap").read_bytes() == (whole / "sensors.mcap").read_bytes()
    topics = ["/sensors/s1", "/sensors/s2", "/sensors/s3"]
    got = read_arrivals(blocked / "sensors.mcap", topics, 1, STEPS + 1)
    t = np.arange(STEPS + 1, dtype=float)
    assert got["/sensors/s1"] is None
    np.testing.assert_array_equal(got["/sensors/s2"][0], t + 1.0)
    np.testing.assert_array_equal(got["/sensors/s3"][0], t + 3.0)


@pytest.mark.parametrize("late", ["reprocess", "retrodict"])
def test_peak_memory_does_not_grow_with_the_instants(tmp_path, monkeypatch, late) -> None:
    """The Python allocations' peak (tracemalloc: numpy's arrays included) of a whole `run`
    with late sensors in blocks of 1000 instants, a recording decimated to 150 points per
    series: twice the instants, the same peak within 10 % (the whole run holds its plans'
    maps, estimates and per-instant sums)."""
    import tracemalloc

    import fusionlog.core.architectures.long_log as long_log
    from fusionlog.core import decimate
    from fusionlog.scenario import load_scenario
    from fusionlog.stages.run import run_pipeline

    monkeypatch.setenv("FUSIONLOG_TIME_BLOCK", "1000")
    monkeypatch.setattr(long_log, "HORIZONS", (512,))
    monkeypatch.setattr(decimate, "DECIMATE_ABOVE", 500)
    monkeypatch.setattr(decimate, "BUCKETS", 50)
    spy = _Spy(monkeypatch)
    archs = ["CKF", "MSC", "SKF:s3"]
    path = _scenario(tmp_path, late, archs)
    peaks = []
    for K in (2_000, 10_000, 20_000):  # the first: what is imported on first use
        sc = load_scenario(path, steps=K)
        tracemalloc.start()
        try:
            run_pipeline(sc, tmp_path / str(K), archs=archs, force=True)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    assert spy.estimated == spy.evaluated == 3 + 11 + 21  # every log in blocks (K + 1 instants)
    assert peaks[2] <= 1.1 * peaks[1], peaks
