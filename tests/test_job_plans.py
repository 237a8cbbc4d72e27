"""The plan caches of the jobs a process computes blocks of (`driver.JobPlans`), passed to the
Monte Carlo tasks explicitly (issue 29: no module-global cache)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fusionlog.core.model import ajgl2009
from fusionlog.driver import JobPlans
from fusionlog.scenario import load_scenario, scenario_with
from fusionlog.stages.montecarlo import Job, block_sums

AJGL = Path(__file__).resolve().parents[1] / "pipeline" / "ajgl2009.toml"


def test_a_job_keeps_its_plan_cache_and_the_oldest_job_goes_first() -> None:
    plans = JobPlans(size=2)
    system = ajgl2009()
    times = np.arange(6.0)
    a = plans.of("a", system, times)
    assert plans.of("a", system, times) is a
    assert a.steps == 5
    b = plans.of("b", system, times)
    assert plans.of("a", system, times) is a  # "a" used last: "b" is the oldest now
    plans.of("c", system, times)
    assert plans.of("a", system, times) is a
    assert plans.of("b", system, times) is not b  # dropped, made anew


def test_the_blocks_of_a_job_share_its_plans_and_give_the_same_sums() -> None:
    """Two blocks of one job through one JobPlans compile each architecture once (the second
    block finds the plans the first compiled); the sums equal those of a call without one."""
    sc = scenario_with(load_scenario(AJGL), runs=40, steps=6)
    job = Job(sc, ("CKF", "MSC-GMF"), "t")
    plans = JobPlans()
    first = block_sums(job, 0, 20, plans=plans)
    compiled = dict(plans.of("t", sc.system, sc.times).plans)
    assert {a for a, _ in compiled} == {"CKF", "MSC-GMF"}
    second = block_sums(job, 20, 20, plans=plans)
    after = plans.of("t", sc.system, sc.times).plans
    assert all(after[k] is p for k, p in compiled.items()) and len(after) == len(compiled)
    alone = block_sums(job, 20, 20)
    for a in job.archs:
        np.testing.assert_array_equal(second.sums[a].sse, alone.sums[a].sse)
        np.testing.assert_array_equal(second.sums[a].count, alone.sums[a].count)
    assert first.runs == second.runs == 20
