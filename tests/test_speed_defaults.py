"""The defaults chosen for speed (issue 23): where a sweep runs without --workers."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_helpers import ok

from fusionlog.stages.grid import grid_points, parse_vary

ROOT = Path(__file__).resolve().parents[1]
AJGL = ROOT / "pipeline" / "ajgl2009.toml"


def test_default_executor_follows_the_size_of_the_work(tmp_path: Path, monkeypatch) -> None:
    """Without --workers: a sweep of a few seconds runs here (a cluster's start would cost
    more); a large one would go to a LocalCluster (only the decision is checked: no cluster)."""
    from fusionlog.stages import sweep

    res = ok("sweep", AJGL, "--vary", "scenario.dt=1,2", "--runs", "100", "--arch", "CKF",
             "--out-dir", tmp_path / "small")  # fmt: skip
    assert "in this process" in res.stdout
    small = grid_points(AJGL, [parse_vary("scenario.dt=1,2")], runs=100)
    large = grid_points(AJGL, [parse_vary("scenario.dt=1,2")], runs=10**7)
    archs = [("CKF", "MSC")] * 2
    assert sweep.estimated_seconds(large, archs) == pytest.approx(
        10**5 * sweep.estimated_seconds(small, archs)
    )
    monkeypatch.setattr(sweep, "default_workers", lambda: 2)
    assert sweep.small_work(small, archs) and not sweep.small_work(large, archs)
    monkeypatch.setattr(sweep, "default_workers", lambda: 1)
    assert sweep.small_work(large, archs)
