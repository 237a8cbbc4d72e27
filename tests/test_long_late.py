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

from pathlib import Path

import numpy as np
import pytest
from long_helpers import (
    EQUAL,
    LATE_SENSORS,
    OfLargest,
    Spy,
    estimates_close,
    late_toml,
    pipeline_peaks,
    series_close,
    summaries,
    summaries_close,
    whole_and_blocked,
)

import fusionlog.driver.long_log as driver_long_log
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.arrival import read_arrivals
from fusionlog.stages.evaluator.long_evaluator import LongEvaluator

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
    """Two sensors late by fixed latencies of 3 and 1 instants, a third on time."""
    path = tmp / f"{late}.toml"
    path.write_text(late_toml("long_late", 34, steps, LATE_SENSORS, archs, late))
    return path


def _spy(mp: pytest.MonkeyPatch) -> Spy:
    """Counts the blocks of time the estimate and evaluate stages took (the blocked path)."""
    return Spy(mp, blocks={"estimated": (driver_long_log, "long_estimates")},
               calls={"evaluated": (LongEvaluator, "add")})  # fmt: skip


@pytest.fixture(
    scope="module",
    params=[(p, v) for p in POLICIES for v in ("plans of the whole log", "steady plans of 512")],
    ids=lambda p: f"{p[0]}, {p[1]}",
)
def late_runs(tmp_path_factory, request):
    """One policy's log of 1200 instants taken whole and in blocks of 50: with late plans over
    all of it, and with late plans of 512 instants standing for it (their steady middle
    repeated, what a log longer than the horizons takes)."""
    late, variant = request.param
    archs = archs_of(late, ARCHS if variant == "plans of the whole log" else STEADY_ARCHS)
    tmp = tmp_path_factory.mktemp(f"late-{late}")
    sc = _scenario(tmp, late, archs)
    horizons = None if variant == "plans of the whole log" else (512,)
    whole, blocked, spy = whole_and_blocked(sc, tmp, 50, horizons=horizons, spy=_spy)
    return late, archs, whole, blocked, spy


def test_the_blocked_log_went_in_blocks(late_runs) -> None:
    """Both stages took the log's 24 blocks of time (not the whole run at once)."""
    spy = late_runs[-1]
    assert (spy.estimated, spy.evaluated) == (24, 24)


def test_blocked_estimates_equal_the_whole_log(late_runs) -> None:
    """Every architecture's means (to rounding) and covariances (to the bit), across edges
    that late readings cross."""
    _, archs, whole, blocked, _ = late_runs
    estimates_close(whole, blocked, archs, mean=OfLargest(RTOL), cov=EQUAL)
    prov = McapFile(blocked / "estimates.mcap").metadata["fusionlog.provenance"]
    assert prov["measurement_pattern"] == "complete"


#: The exact analysis of late plans propagates the joint moments of the truth x_k and the
#: plan's state (`wrap`'s D = 0: no error form), so its values are differences of numbers of
#: the size of the truth's variance, var(position_k) ~ q k^3 / 3 (constant velocity, q = 0.16):
#: a few tens of roundings of that, absolute, at the log's end (the whole log's analysis) --
#: the short plans' analysis stops at the horizon's middle, where it is converged and smaller.
EXACT_ATOL = 32 * np.finfo(float).eps * 0.16 * STEPS**3 / 3


def _close(a, b, steady: bool) -> None:
    """RTOL relative, 1e-15 absolute; with short plans standing for the log, the exact values
    within `EXACT_ATOL` and the bound's worst step passed over (an argmax over ratios equal to
    roundings)."""
    exact_atol, skip = (EXACT_ATOL, ("worst_step",)) if steady else (None, ())
    summaries_close(a, b, rtol=RTOL, atol=1e-15, exact_atol=exact_atol, skip=skip)


def test_blocked_summary_equals_the_whole_log(late_runs) -> None:
    """Monte Carlo metrics, the exact values (the late plans' analysis at each block's
    instants), the bound check and the policy, as from the whole log; with short plans standing
    for it, the exact values within the whole log's own rounding (`EXACT_ATOL`)."""
    late, archs, whole, blocked, _ = late_runs
    a, b = summaries(whole, blocked)
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
    series_close(whole, blocked, 1e-9, atol, EXACT_ATOL if steady else None)


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


@pytest.mark.memory
@pytest.mark.parametrize("late", ["reprocess", "retrodict"])
def test_peak_memory_does_not_grow_with_the_instants(tmp_path, monkeypatch, late) -> None:
    """The Python allocations' peak (tracemalloc: numpy's arrays included) of a whole `run`
    with late sensors in blocks of 1000 instants, a recording decimated to 150 points per
    series: twice the instants, the same peak within 10 % (the whole run holds its plans'
    maps, estimates and per-instant sums)."""
    import fusionlog.core.architectures.long_log as long_log

    monkeypatch.setattr(long_log, "HORIZONS", (512,))
    spy = _spy(monkeypatch)
    archs = ["CKF", "MSC", "SKF:s3"]
    path = _scenario(tmp_path, late, archs)
    sizes = (2_000, 10_000, 20_000)
    peaks = pipeline_peaks(tmp_path, monkeypatch, path, archs, sizes, 1000, 500, 50)
    assert spy.estimated == spy.evaluated == 3 + 11 + 21  # every log in blocks (K + 1 instants)
    assert peaks[2] <= 1.1 * peaks[1], peaks
