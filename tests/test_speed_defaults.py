"""The defaults chosen for speed (issue 23): where a sweep runs without --workers, and the
LocalCluster started in the background while this process computes."""

from __future__ import annotations

import threading
import time
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


def _square(x: int) -> int:
    return x * x


class _SlowCluster:
    """A stand-in for a LocalCluster's DaskExecutor whose start ends only once a task has run
    in this process (no timing in the test: the events order it)."""

    workers, description = 2, "on a LocalCluster of 2 worker processes"

    def __init__(self) -> None:
        self.first_done, self.started = threading.Event(), threading.Event()
        self.got: list[int] = []
        self.closed = False

    def __enter__(self):
        assert self.first_done.wait(30)
        self.started.set()
        return self

    def map(self, tasks, desc):
        self.got = [args[0] for _, args in tasks]
        return iter(fn(*args) for fn, args in tasks)

    def release(self) -> None:
        pass

    def __exit__(self, *exc) -> None:
        self.closed = True


def test_warm_start_computes_here_until_the_cluster_is_up() -> None:
    """Tasks from the front run in this process while the cluster starts, the rest on it; the
    results come in task order and the cluster is closed at the end."""
    from fusionlog.stages.warm_start import WarmStartExecutor

    cluster = _SlowCluster()

    def task(x: int) -> int:
        cluster.first_done.set()
        assert cluster.started.wait(30)
        time.sleep(0.05)  # the cluster's thread marks it ready meanwhile
        return _square(x)

    tasks = [(task, (i,)) for i in range(40)]
    with WarmStartExecutor(cluster) as ex:  # type: ignore[arg-type]
        results = list(ex.map(tasks, "test"))
    assert results == [i * i for i in range(40)]
    here = 40 - len(cluster.got)
    assert 1 <= here < 40 and cluster.got == list(range(here, 40))
    assert f"the first {here} of 40 tasks here" in ex.description and cluster.closed
