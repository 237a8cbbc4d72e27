"""Issue 34: the per-sensor rules (MSC, MSC-GMF, CI, AVG, ICI, EI) on a long one-run log with
late sensors whose delays are drawn per reading or recorded, or whose readings are missing, in
blocks of time (`core.latency_blocks`: the stacked locals carried, the rule on their current
blocks), and HKF's exact analysis where correlated readings arrive apart (`core.latency_apart`).

The whole log taken at once is the reference, by another route: its estimates and exact values
come from the late plans of the run's arrival pattern (`latency_stacked.fused_plan`, and
`latency_joint.joint_fused_plan` -- J from the affine maps on z as taken -- where correlated
readings arrive apart), analysed by `core.exact.analyse` (conditional on the drawn delays),
themselves checked against filters written from the formulas in tests/test_latency*.py. The
blocks carry each local's stacked filter, the locals' joint error covariance (with the raw
noises still to be read where correlated readings arrive apart) and HKF's error covariance.
Independently of the whole run: MSC-GMF and AVG report their true error covariance, so their
bound check holds with ratio 1 at every instant (exact values equal to their P), and CI's is
conservative. Blocks of 50 (FUSIONLOG_TIME_BLOCK) cut a log of 600 with latencies of 0 to 3
instants, so readings cross the edges. Tolerances as tests/test_long_late_random.py's (its
`RTOL`, `EXACT_ATOL`).
"""

from __future__ import annotations

import json

import pytest
from cli_helpers import ok
from long_helpers import (
    OfLargest,
    estimates_close,
    pipeline_peaks,
    summaries,
    summaries_close,
    time_block,
    whole_and_blocked,
)
from test_long_late_random import (
    BLOCK,
    EXACT_ATOL,
    RTOL,
    STEPS,
    _recorded,
    _scenario,
    _spy,
    case_runs,
    each_case,
)

from fusionlog.io.mcap import McapFile

#: The per-sensor rules; where correlated readings arrive apart HKF too (its exact analysis).
RULES = ["MSC", "MSC-GMF", "CI", "AVG", "ICI", "EI"]

#: (name, s3's latency, missing readings, s1 and s3 correlated)
CASES = [
    ("random delays", "{min = 1.0, max = 3.0}", False, False),
    ("random delays, correlated sensors apart, missing", "{min = 0.0, max = 2.0}", True, True),
    ("fixed latencies, missing readings", "3.0", True, False),
]


#: The whole run takes the rules' plans, and HKF's with them (information form), the blocks
#: the plan-free filters: the means differ by up to RTOL * max|mean| (< 100 + STEPS), so a
#: squared error (|e| a few sigma, < 10) moves by 2 |e| that.
METRIC_ATOL = 2 * 10 * RTOL * (100 + STEPS)


def _close(a, b) -> None:
    """summary.json's values: exact ones (and the bound's) within `EXACT_ATOL`, the Monte
    Carlo metrics within `METRIC_ATOL` (relative RTOL either way), the rest equal but the
    bound's worst step (an argmax among ratios equal to rounding)."""
    summaries_close(a, b, rtol=RTOL, atol=METRIC_ATOL, exact_atol=EXACT_ATOL, skip=("worst_step",))


def _archs(correlated: bool) -> list[str]:
    return RULES + ["HKF"] if correlated else RULES


@pytest.fixture(**each_case(CASES))
def runs(tmp_path_factory, request):
    """One case's log of 600 instants taken whole and in blocks of 50."""
    case, late = request.param
    return case_runs(tmp_path_factory.mktemp("late-rules"), case, late, _archs(case[3]))


def test_the_blocked_log_went_in_blocks(runs) -> None:
    """The estimate, the evaluation and the exact analysis took the log's 12 blocks of time."""
    spy = runs[-2]
    assert (spy.estimated, spy.evaluated, spy.exact) == (12, 12, 12)


def test_blocked_estimates_equal_the_whole_log(runs) -> None:
    """Every rule's means and covariances across edges that late readings cross (the means
    grow to ~|100 - 600|: 1e-12 of the largest); the measurement pattern as the whole run's."""
    _, _, whole, blocked, _, archs = runs
    estimates_close(whole, blocked, archs, mean=OfLargest(RTOL), cov=OfLargest(RTOL))
    pa, pb = (McapFile(d / "estimates.mcap").metadata["fusionlog.provenance"] for d in runs[2:4])
    assert pa["measurement_pattern"] == pb["measurement_pattern"]


def test_blocked_summary_equals_the_whole_log(runs) -> None:
    """Monte Carlo metrics, exact values (conditional on drawn delays), the bound check and the
    policy as from the whole log; MSC-GMF's and AVG's P their true error covariance (ratio 1),
    CI's an upper bound."""
    name, late, whole, blocked, _, archs = runs
    a, b = summaries(whole, blocked)
    _close(b, a)
    assert b["late"] == late
    for arch in archs:
        ex = b["architectures"][arch]["expected"]
        assert ex["mse"] is not None and ex.get("conditional", False) == ("random" in name)
    for arch in ("MSC-GMF", "AVG", "CI"):
        bound = b["architectures"][arch]["bound"]
        assert bound["holds"], arch
    for arch in ("MSC-GMF", "AVG"):  # E[e e'] = P: the largest ratio 1 to rounding
        assert b["architectures"][arch]["bound"]["worst"] == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("late", ["reprocess", "neglect"])
def test_a_recorded_replay_in_blocks_equals_the_whole_log(tmp_path, late) -> None:
    """A replay whose late sensor's arrivals are its messages' log times, with gaps, through
    the rules: estimates and summary (with its NIS per sensor) as the whole log's."""
    sc = _recorded(tmp_path, late, True)
    archs = RULES
    sc.write_text(sc.read_text().replace('["CKF", "HKF", "SKF:b"]', json.dumps(archs)))
    whole, blocked, spy = whole_and_blocked(sc, tmp_path, BLOCK, spy=_spy)
    K1 = McapFile(whole / "sensors.mcap").steps()
    assert spy.estimated == spy.evaluated == -(-K1 // BLOCK) > 1
    # a random walk of std < 10
    estimates_close(whole, blocked, archs, mean=(0, 1e-12), cov=(0, 1e-12))
    sa, sb = summaries(whole, blocked)
    _close(sb, sa)
    assert "nis" in sb["architectures"]["MSC"]


@pytest.mark.memory
def test_peak_memory_does_not_grow_with_the_instants(tmp_path, monkeypatch) -> None:
    """The Python allocations' peak (tracemalloc) of a whole `run` of the rules with random
    delays, missing readings and correlated readings arriving apart, in blocks of 1000
    instants, a recording decimated to 150 points per series: twice the instants, the same
    peak within 10 % (the whole run holds its per-run plans' maps)."""
    spy = _spy(monkeypatch)
    archs = ["MSC-GMF", "CI", "EI", "HKF"]
    path = _scenario(tmp_path, "{min = 0.0, max = 2.0}", True, True, "reprocess", archs=archs)
    sizes = (2_000, 10_000, 20_000)
    peaks = pipeline_peaks(tmp_path, monkeypatch, path, archs, sizes, 1000, 500, 50)
    assert spy.estimated == spy.evaluated == spy.exact == 3 + 11 + 21
    assert peaks[2] <= 1.1 * peaks[1], peaks


# -- a late log without an exact analysis: a nonlinear truth --------------------------------

TURN = """
[scenario]
name = "late_turn"
steps = 599
runs = 1
seed = 5
dt = 1.0
state_names = ["x", "vx", "y", "vy", "omega"]
[model]
{model}
[prior]
mean = [0.0, 15.0, 500.0, 0.0, 0.02]
cov = [[100.0, 0.0, 0.0, 0.0, 0.0], [0.0, 16.0, 0.0, 0.0, 0.0], [0.0, 0.0, 100.0, 0.0, 0.0],
       [0.0, 0.0, 0.0, 16.0, 0.0], [0.0, 0.0, 0.0, 0.0, 4.0e-4]]
[[sensors]]
name = "s1"
H = [[1.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0]]
R = [[25.0, 0.0], [0.0, 25.0]]
dropout = 0.2
[[sensors]]
name = "s2"
H = [[1.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0]]
R = [[16.0, 0.0], [0.0, 16.0]]
latency = {{min = 1.0, max = 3.0}}
[estimate]
architectures = ["MSC", "CI", "CKF"]
late = "reprocess"
{filter}
"""

#: the truth: a coordinated turn (EKF for its own scenario); the filters: constant velocity
COORDINATED = 'kind = "coordinated-turn"\nq = [0.05, 0.05]\nq_turn = 1.0e-5'
LINEAR = """F = [[1.0, 1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0, 0.0],
     [0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0, 1.0]]
Q = [[0.1, 0.1, 0.0, 0.0, 0.0], [0.1, 0.5, 0.0, 0.0, 0.0], [0.0, 0.0, 0.1, 0.1, 0.0],
     [0.0, 0.0, 0.1, 0.5, 0.0], [0.0, 0.0, 0.0, 0.0, 1.0e-5]]"""


def test_a_late_log_without_exact_analysis_is_evaluated_in_blocks(tmp_path, monkeypatch) -> None:
    """Linear late filters (`estimate --model`, constant velocity) on a coordinated-turn truth,
    delays drawn and readings missing: no exact analysis (a nonlinear truth), so the metrics,
    the PCRB and the rest are evaluated in blocks as an on-time log's (they read the estimates
    and readings only), the summary the whole log's."""
    truth, model = tmp_path / "truth.toml", tmp_path / "model.toml"
    truth.write_text(TURN.format(model=COORDINATED, filter='filter = "EKF"'))
    model.write_text(TURN.format(model=LINEAR, filter=""))
    sensors, est = tmp_path / "s.mcap", tmp_path / "e.mcap"
    time_block(monkeypatch, None)
    ok("simulate", truth, "-o", sensors)
    ok("estimate", sensors, "--model", model, "-o", est)
    got = {}
    for block in (None, BLOCK):
        if block is not None:
            time_block(monkeypatch, block)
            spy = _spy(monkeypatch)
        out = tmp_path / f"{block}.json"
        ok("evaluate", sensors, est, "-o", tmp_path / f"{block}.rrd", "--summary", out)
        got[block] = json.loads(out.read_text())
    assert spy.evaluated == 12 and spy.exact == 0
    whole, blocked = got[None], got[BLOCK]
    _close(blocked, whole)
    assert blocked["architectures"]["CKF"]["expected"] is None and blocked["late"] == "reprocess"
    assert blocked["pcrb"]
