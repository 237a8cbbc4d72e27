"""Issue 34: a long one-run log with late sensors whose delays are drawn per reading or
recorded, or whose readings are missing, in blocks of time (`core.latency_blocks`).

The whole log taken at once is the reference: its estimates come from the stacked model's
filters over the whole run (`core.latency_replay`, checked against filters written from the
formulas in tests/test_latency*.py), its exact values from the late plans of the run's arrival
pattern analysed by `core.exact.analyse` (conditional on the drawn delays). Blocks of 50
instants (the hidden setting FUSIONLOG_TIME_BLOCK) cut a log of 600, so readings taken before an
edge arrive after it (latencies of 1 to 3 instants). Blocked and whole run the same filter
formulas; the means differ by where the recursion is cut (roundings), the exact values by the
route (the stacked filter's own P against the plans' joint moments of truth and estimator,
whose rounding grows with the truth's variance: `EXACT_ATOL`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from long_helpers import (
    OfLargest,
    Spy,
    estimates_close,
    late_toml,
    pipeline_peaks,
    position_sensor,
    run,
    series_close,
    summaries,
    summaries_close,
    whole_and_blocked,
)
from mcap.writer import Writer

import fusionlog.stages.late_blocks as late_blocks
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.arrival import read_arrivals
from fusionlog.stages.evaluator.long_evaluator import LongEvaluator
from fusionlog.stages.evaluator.long_late import LongLateExact

#: The architectures the blocked late path covers (`core.latency_blocks`): the filters fusing
#: every sensor and one sensor's.
ARCHS = ["CKF", "HKF", "SKF", "SKF:s3"]
STEPS = 599
BLOCK = 50

#: (name, s3's latency, missing readings, s1 and s3 correlated)
CASES = [
    ("random delays", "{min = 1.0, max = 3.0}", False, False),
    ("random delays, missing readings", "{min = 1.0, max = 3.0}", True, False),
    ("fixed latencies, missing readings", "3.0", True, False),
    ("random delays, correlated sensors apart", "{min = 0.0, max = 2.0}", True, True),
]


def _archs(correlated: bool) -> list[str]:
    """HKF fuses correlated readings arriving apart as independent (its error correlated
    across instants): on its own in `test_hkf_with_correlated_readings_apart_in_blocks`."""
    return [a for a in ARCHS if a != "HKF"] if correlated else ARCHS


def _scenario(tmp: Path, s3: str, missing: bool, correlated: bool, late: str, steps=STEPS,
              archs: list[str] | None = None) -> Path:  # fmt: skip
    """s1 on time, s2 1 s late, s3 late by `s3` (TOML: a latency or its range); with `missing`,
    readings dropped (s1 20 %, s3 30 %) and s2 every other instant; s1 and s3 `correlated`."""
    archs = _archs(correlated) if archs is None else archs
    drops = ("dropout = 0.2\n", "period = 2.0\n", "dropout = 0.3\n") if missing else ("",) * 3
    corr = '[[correlations]]\nsensors = ["s1", "s3"]\ncov = [[0.4]]\n' if correlated else ""
    sensors = (
        position_sensor("s1", 1.0, None, drops[0])
        + position_sensor("s2", 2.0, "1.0", drops[1])
        + position_sensor("s3", 0.5, s3, drops[2])
        + corr
    )
    path = tmp / f"{late}.toml"
    path.write_text(late_toml("long_late_random", 341, steps, sensors, archs, late))
    return path


def _spy(mp: pytest.MonkeyPatch) -> Spy:
    """Counts the blocks of time the late path estimated and evaluated, and the exact blocks."""
    calls = {"evaluated": (LongEvaluator, "add"), "exact": (LongLateExact, "window")}
    return Spy(mp, blocks={"estimated": (late_blocks, "late_estimates")}, calls=calls)


def each_case(cases) -> dict:
    """The module-scoped fixture's parameters: each case under each policy."""
    params = [(c, p) for c in cases for p in ("reprocess", "neglect")]
    return dict(scope="module", params=params, ids=lambda p: f"{p[0][0]}, {p[1]}")


def case_runs(tmp: Path, case, late: str, archs: list[str]):
    """One case's log of 600 instants taken whole and in blocks of 50: (its name, the policy,
    whole, blocked, the blocked run's spy, the architectures)."""
    name, s3, missing, correlated = case
    sc = _scenario(tmp, s3, missing, correlated, late, archs=archs)
    whole, blocked, spy = whole_and_blocked(sc, tmp, BLOCK, spy=_spy)
    return name, late, whole, blocked, spy, archs


@pytest.fixture(**each_case(CASES))
def runs(tmp_path_factory, request):
    """One case's log of 600 instants taken whole and in blocks of 50."""
    case, late = request.param
    return case_runs(tmp_path_factory.mktemp("late-random"), case, late, _archs(case[3]))


def test_the_blocked_log_went_in_blocks(runs) -> None:
    """Both stages and the exact analysis took the log's 12 blocks of time."""
    spy = runs[-2]
    assert (spy.estimated, spy.evaluated, spy.exact) == (12, 12, 12)


def test_the_sensors_log_is_the_whole_runs(runs) -> None:
    """The simulation drawn in blocks (the delays too, from their own stream) writes the whole
    run's readings and arrivals."""
    name, _, whole, blocked, *_ = runs
    topics = ["/truth", "/sensors/s1", "/sensors/s2", "/sensors/s3"]
    a = McapFile(whole / "sensors.mcap").read_all(topics)
    b = McapFile(blocked / "sensors.mcap").read_all(topics)
    for t in topics:
        np.testing.assert_array_equal(a[t], b[t], err_msg=t)
    ga, gb = (read_arrivals(d / "sensors.mcap", topics[1:], 1, STEPS + 1) for d in (whole, blocked))
    assert ga["/sensors/s1"] is None and gb["/sensors/s1"] is None
    for t in topics[2:]:
        np.testing.assert_array_equal(ga[t], gb[t], err_msg=t)
    t = np.arange(STEPS + 1, dtype=float)
    delay = gb["/sensors/s3"][0] - t
    ok = ~np.isnan(delay)
    lo, hi = (1.0, 3.0) if "correlated" not in name else (0.0, 2.0)
    if "random" in name:  # drawn uniform in [lo, hi]: spread over it, not one value
        assert ((delay[ok] >= lo) & (delay[ok] <= hi)).all() and np.ptp(delay[ok]) > 0.9 * (hi - lo)
    else:
        np.testing.assert_array_equal(delay[ok], 3.0)


#: Means grow to ~|100 - 600| (velocity -1): blocking reorders roundings of O(1e-16) relative in
#: a contractive recursion, so 1e-12 of the largest mean; covariances (of order 1) likewise.
RTOL = 1e-12


def test_blocked_estimates_equal_the_whole_log(runs) -> None:
    """Every architecture's means and covariances across edges that late readings cross; the
    measurement pattern recorded as the whole run's."""
    _, _, whole, blocked, _, archs = runs
    estimates_close(whole, blocked, archs, mean=OfLargest(RTOL), cov=OfLargest(RTOL))
    pa, pb = (McapFile(d / "estimates.mcap").metadata["fusionlog.provenance"] for d in runs[2:4])
    assert pa["measurement_pattern"] == pb["measurement_pattern"]


#: The plans' exact analysis propagates the joint moments of the truth and the plan's state,
#: so its values are differences of numbers of the size of the truth's variance,
#: var(position_k) ~ q k^3 / 3 (constant velocity, q = 0.16): a few tens of its roundings.
EXACT_ATOL = 32 * np.finfo(float).eps * 0.16 * STEPS**3 / 3


def _close(a, b) -> None:
    """RTOL relative, 1e-15 absolute, the exact values within `EXACT_ATOL`; the bound's worst
    step passed over (the filters' bound ratio is 1 at every instant, P their error
    covariance: its argmax is among ratios equal to roundings)."""
    summaries_close(a, b, rtol=RTOL, atol=1e-15, exact_atol=EXACT_ATOL, skip=("worst_step",))


def test_blocked_summary_equals_the_whole_log(runs) -> None:
    """Monte Carlo metrics, the exact values (conditional on the drawn delays where they are
    drawn), the bound check and the policy, as from the whole log."""
    name, late, whole, blocked, _, archs = runs
    a, b = summaries(whole, blocked)
    _close(b, a)
    assert b["late"] == late
    for arch in archs:
        ex = b["architectures"][arch]["expected"]
        assert ex["mse"] is not None and ex.get("conditional", False) == ("random" in name)
        assert b["architectures"][arch]["bound"]["holds"]


def test_blocked_recording_equals_the_whole_log(runs) -> None:
    """The series drawn: squared errors (|e| a few sigma, < 10 here) move by 2 |e| delta with
    the means' delta <= RTOL * max |mean| (< 100 + STEPS); the exact series as the summary's."""
    _, _, whole, blocked, *_ = runs
    atol = 2 * 10 * RTOL * (100 + STEPS)
    series_close(whole, blocked, 1e-9, atol, EXACT_ATOL)


def test_sub_blocks_of_the_stacked_filters_change_no_number(tmp_path, monkeypatch) -> None:
    """A block of time cut into sub-blocks of the stacked filters (`LATE_BLOCK_BYTES` small:
    a few instants each, the cut inside the blocks of 50): the estimates and the summary as
    the whole run's."""
    import fusionlog.core.latency_blocks as latency_blocks

    sc = _scenario(tmp_path, "{min = 1.0, max = 3.0}", True, False, "reprocess")
    whole = run(sc, tmp_path / "whole", None, monkeypatch)
    monkeypatch.setattr(latency_blocks, "LATE_BLOCK_BYTES", 1 << 15)
    blocked = run(sc, tmp_path / "blocked", BLOCK, monkeypatch)
    estimates_close(whole, blocked, ARCHS, mean=OfLargest(RTOL), cov=OfLargest(RTOL))
    sa, sb = summaries(whole, blocked)
    _close(sb, sa)


def test_hkf_with_correlated_readings_apart_in_blocks(tmp_path, monkeypatch) -> None:
    """HKF on correlated sensors whose readings of one instant arrive apart: estimated and
    evaluated in blocks (its error is correlated across instants: its recursion keeps the raw
    noises still to be read, `core.latency_apart`), estimates and summary the whole run's
    (the plans' exact analysis)."""
    sc = _scenario(tmp_path, "{min = 0.0, max = 2.0}", True, True, "reprocess", archs=ARCHS)
    whole, blocked, spy = whole_and_blocked(sc, tmp_path, BLOCK, spy=_spy)
    assert (spy.estimated, spy.evaluated, spy.exact) == (12, 12, 12)
    a = McapFile(whole / "estimates.mcap").read_all(["/estimates/HKF"])["/estimates/HKF"]
    b = McapFile(blocked / "estimates.mcap").read_all(["/estimates/HKF"])["/estimates/HKF"]
    np.testing.assert_allclose(b[0], a[0], rtol=0, atol=RTOL * np.abs(a[0]).max())
    sa, sb = summaries(whole, blocked)
    _close(sb, sa)


def test_a_recorded_log_s_route_takes_late_sensors_into_account() -> None:
    """The exact analysis of one recorded log (the ``one-log`` route) with a sensor late by a
    fixed 2 s and readings missing equals the late plan's analysis (the ``plans`` route), not
    the covariances of the same readings fused on time (0.30 against 0.48 at the end, before
    the route knew of late sensors)."""
    from fusionlog.core.routes import shared_expected
    from fusionlog.driver import PlanCache
    from fusionlog.scenario import load_scenario

    K = 30
    system = load_scenario(Path(__file__).parents[1] / "pipeline" / "latency.toml").system
    plans = PlanCache(system, K)
    mask = np.ones((K + 1, system.m), bool)
    mask[::3, 0] = False
    got = {
        route: shared_expected(
            route, system, system, ["CKF"], mask, K, plans.criterion, lambda a: plans.plan(a, mask)
        )("CKF").mse  # fmt: skip
        for route in ("one-log", "plans")
    }
    np.testing.assert_array_equal(got["one-log"], got["plans"])


# -- a recorded replay: arrivals from the messages' log times ---------------------------------

NS = 1_000_000_000
T0 = 1_700_000_000 * NS
#: the recorded replay's architectures
RECORDED_ARCHS = ["CKF", "HKF", "SKF:b"]


def _recorded(tmp: Path, late: str, gaps: bool) -> Path:
    """A JSON MCAP of two sensors of one random walk: a on time every 0.1 s, b stamped at 0.05 +
    0.1 i and logged 0 to 0.3 s late (uniform); with `gaps`, a fifth of b's readings left out.
    The scenario replays it with b's arrival its log time."""
    rng = np.random.default_rng(7)
    N = 300
    x = np.cumsum(rng.normal(0, 0.2, 2 * N))
    a = [(T0 + i * NS // 10, T0 + i * NS // 10, x[2 * i] + rng.normal(0, 0.7)) for i in range(N)]
    b = []
    for i in range(N):
        stamp = T0 + (i * 100 + 50) * NS // 1000
        if gaps and rng.random() < 0.2:
            continue
        logged = stamp + round(rng.uniform(0, 0.3) * NS)
        b.append((stamp, logged, x[2 * i + 1] + rng.normal(0, 0.4)))
    schema = {"type": "object", "properties": {"header": {"type": "object"},
                                               "v": {"type": "number"}}}  # fmt: skip
    with open(tmp / "log.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("Reading", "jsonschema", json.dumps(schema).encode())
        ch = {t: w.register_channel(t, "json", sid) for t in ("/a", "/b")}
        events = sorted([(lg, "/a", s, v) for s, lg, v in a] + [(lg, "/b", s, v) for s, lg, v in b])
        for lg, t, stamp, v in events:
            body = {"header": {"stamp": {"sec": stamp // NS, "nanosec": stamp % NS}}, "v": v}
            w.add_message(ch[t], log_time=lg, data=json.dumps(body).encode(), publish_time=lg)
        w.finish()
    sensor = 'source = "log.mcap"\nvalues = ["v"]\ntime = "header.stamp"\nH = [[1.0]]\n'
    text = f"""
[scenario]
name = "recorded_late"
state_names = ["x"]
[model]
kind = "continuous"
A = [[0.0]]
Qc = [[0.4]]
[prior]
mean = [0.0]
cov = [[4.0]]
[[sensors]]
name = "a"
topic = "/a"
{sensor}R = 0.49
[[sensors]]
name = "b"
topic = "/b"
{sensor}R = 0.16
arrival = "log_time"
[estimate]
architectures = {json.dumps(RECORDED_ARCHS)}
late = "{late}"
"""
    path = tmp / "recorded.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("gaps", [False, True], ids=["every reading", "gaps"])
@pytest.mark.parametrize("late", ["reprocess", "neglect"])
def test_a_recorded_replay_in_blocks_equals_the_whole_log(tmp_path, late, gaps):
    """A replay whose late sensor's arrivals are its messages' log times (600 instants, blocks
    of 50): estimates, summary (mean trace, NIS per sensor) and recording as the whole log's,
    the arrivals read block by block."""
    sc = _recorded(tmp_path, late, gaps)
    whole, blocked, spy = whole_and_blocked(sc, tmp_path, BLOCK, spy=_spy)
    K1 = McapFile(whole / "sensors.mcap").steps()
    assert spy.estimated == spy.evaluated == -(-K1 // BLOCK) > 1
    # a random walk of std < 10: 1e-12 absolute
    estimates_close(whole, blocked, RECORDED_ARCHS, mean=(0, 1e-12), cov=(0, 1e-12))
    sa, sb = summaries(whole, blocked)
    _close(sb, sa)
    assert "nis" in sb["architectures"]["CKF"]
    series_close(whole, blocked, 1e-9, 1e-12)


@pytest.mark.memory
def test_peak_memory_does_not_grow_with_the_instants(tmp_path, monkeypatch) -> None:
    """The Python allocations' peak (tracemalloc: numpy's arrays included) of a whole `run`
    with random delays and missing readings in blocks of 1000 instants, a recording decimated
    to 150 points per series: twice the instants, the same peak within 10 % (the whole run
    holds its per-run plans' maps, estimates and per-instant sums)."""
    spy = _spy(monkeypatch)
    path = _scenario(tmp_path, "{min = 1.0, max = 3.0}", True, False, "reprocess")
    sizes = (2_000, 10_000, 20_000)
    peaks = pipeline_peaks(tmp_path, monkeypatch, path, ARCHS, sizes, 1000, 500, 50)
    assert spy.estimated == spy.evaluated == spy.exact == 3 + 11 + 21
    assert peaks[2] <= 1.1 * peaks[1], peaks
