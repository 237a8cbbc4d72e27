"""Issue 34: a long one-run log in blocks of time, and recordings sized for a viewer.

The time-block size is the hidden setting FUSIONLOG_TIME_BLOCK, so that a log of a few thousand
instants spans several blocks: its estimates, summary (Monte Carlo and exact values) and
recording must be those of the same log taken whole. Decimation is checked against the
extremes and means computed here from the full series; the memory bound by the peak of the
Python allocations (tracemalloc), which must not grow with the instants.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from long_helpers import (
    estimates_close,
    pipeline_peaks,
    series_close,
    summaries,
    summaries_close,
    whole_and_blocked,
)

from fusionlog.io.mcap import McapFile

PAPER = Path(__file__).resolve().parents[1] / "pipeline" / "ajgl2009.toml"
ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS"]

# Means are ~100 (the paper's position), the filters contractive: blocking changes only the
# order of roundings, 1e-12 absolute on the means; sums over 3000 instants 1e-12 relative.
RTOL = 1e-9


def _close(a, b):
    summaries_close(a, b, rtol=RTOL, atol=1e-12)


@pytest.fixture(scope="module", params=["plans of the whole log", "steady plans of 512"])
def paper_runs(tmp_path_factory, request):
    """The paper's example, one run of 3000 steps, whole and in blocks of 500 instants: with
    plans over all of it, and with plans of 512 instants standing for it (their steady middle
    repeated, `core.architectures.long_log`: what a log longer than the horizons takes)."""
    tmp = tmp_path_factory.mktemp("long")
    horizons = None if request.param == "plans of the whole log" else (512,)
    extra = ("--runs", "1", "--steps", 3000)
    whole, blocked, _ = whole_and_blocked(PAPER, tmp, 500, *extra, horizons=horizons)
    return whole, blocked


def test_blocked_estimates_equal_the_whole_run(paper_runs) -> None:
    """Every architecture's means and covariances, FBS's backward pass across the blocks."""
    estimates_close(*paper_runs, ARCHS, mean=(0, 1e-9), cov=(RTOL, 1e-15))
    prov = McapFile(paper_runs[1] / "estimates.mcap").metadata["fusionlog.provenance"]
    assert prov["measurement_pattern"] == "complete"


def test_blocked_summary_equals_the_whole_run(paper_runs) -> None:
    """Monte Carlo metrics over every instant and the exact analysis (the shared plan's
    covariances at each block's instants) as from the whole run."""
    whole, blocked = summaries(*paper_runs)
    _close(blocked, whole)
    for a in ARCHS:
        assert whole["architectures"][a]["expected"]["mse"] is not None


def _series_close(whole: Path, blocked: Path) -> None:
    """The two recordings draw the same series (a log below the decimation threshold)."""
    series_close(whole, blocked, RTOL, 1e-9)


def test_blocked_recording_equals_the_whole_run(paper_runs) -> None:
    _series_close(*paper_runs)


CSV_REPLAY = """
[scenario]
name = "long_csv"
state_names = ["p", "v"]
[model]
kind = "constant-velocity"
n0 = 0.5
[prior]
mean = [1.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]
[[sensors]]
name = "a"
source = "log.csv"
values = ["a"]
time_unit = "ns"
H = [[1.0, 0.0]]
R = 1.0
[[sensors]]
name = "b"
source = "log.csv"
values = ["b"]
time_unit = "ns"
H = [[1.0, 0.0]]
R = 1.0
[estimate]
architectures = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS"]
"""

TRUTH = """
[truth]
source = "log.csv"
values = ["p", "v"]
states = ["p", "v"]
time_unit = "ns"
match = "exact"
"""


@pytest.mark.parametrize("truth", [False, True], ids=["no truth: NIS", "truth"])
def test_a_replay_in_blocks_equals_the_whole_log(tmp_path, truth) -> None:
    """A recorded CSV log at a regular rate (a replay: its instants from the data) estimated
    and evaluated in blocks of time equals the whole log: every architecture's estimates, the
    summary (NIS per sensor with its whiteness across blocks; with truth, the metrics and
    exact values) and the recording."""
    rng = np.random.default_rng(7)
    K1 = 2600
    t = np.arange(K1) * 0.005
    v = 0.2 * np.cumsum(rng.normal(size=K1)) * 0.07
    pos = 1.0 + np.cumsum(v) * 0.005
    rows = "\n".join(
        f"{round(ti * 1e9)},{p + rng.normal():.6f},{p + rng.normal():.6f},{p:.9f},{vi:.9f}"
        for ti, p, vi in zip(t, pos, v, strict=True)
    )
    (tmp_path / "log.csv").write_text("time,a,b,p,v\n" + rows + "\n")
    (tmp_path / "replay.toml").write_text(CSV_REPLAY + (TRUTH if truth else ""))
    dirs = whole_and_blocked(tmp_path / "replay.toml", tmp_path, 400)[:2]
    estimates_close(*dirs, ARCHS, mean=(0, 1e-9), cov=(RTOL, 1e-15))
    whole, blocked = summaries(*dirs)
    _close(blocked, whole)
    assert ("expected" in whole["architectures"]["CKF"]) == truth
    assert "nis" in whole["architectures"]["CKF"]
    _series_close(*dirs)


@pytest.mark.memory
def test_peak_memory_does_not_grow_with_the_instants(tmp_path, monkeypatch) -> None:
    """The Python allocations' peak (tracemalloc: numpy's arrays included) of a whole `run`
    in blocks of 1000 instants, with a recording decimated to 150 points per series: twice
    the instants, the same peak within 10 % (the whole run at once holds its estimates and
    per-instant sums: +50 % here from 10^4 to 2*10^4 instants)."""
    import fusionlog.core.architectures.long_log as long_log

    monkeypatch.setattr(long_log, "HORIZONS", (512,))
    archs, sizes = ["CKF", "MSC-GMF", "FBS"], (2_000, 10_000, 20_000)
    peaks = pipeline_peaks(tmp_path, monkeypatch, PAPER, archs, sizes, 1000, 500, 50, runs=1)
    assert peaks[2] <= 1.1 * peaks[1], peaks
