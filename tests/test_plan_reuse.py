"""`fusionlog run` hands the estimate stage's per-run plans of a block to the evaluation's exact
analysis (a `driver.KeptPlans` both stages' caches are given): the same plan for the same
model and masks, never another block's, and the run's summary is that of the stages run one
by one."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from cli_helpers import ok

from fusionlog.core.model import ajgl2009
from fusionlog.core.simulate import simulate
from fusionlog.driver import KeptPlans, PlanCache

ROOT = Path(__file__).resolve().parents[1]
DROPOUT = ROOT / "pipeline" / "ajgl2009_dropout.toml"


def dropped(seed: int) -> np.ndarray:
    _, z = simulate(ajgl2009(), 8, seed, 0, 40)
    z[np.random.default_rng(seed).random(z.shape) < 0.2] = np.nan
    return z


def test_a_block_gets_its_own_plans_back_and_no_other():
    archs = ["CKF", "MSC-GMF"]
    z1, z2 = dropped(1), dropped(2)
    kept = KeptPlans()
    first, _ = PlanCache(ajgl2009(), 8, kept=kept).block_plans(archs, z1)
    again, _ = PlanCache(ajgl2009(), 8, kept=kept).block_plans(archs, z1)  # a later stage's
    other, _ = PlanCache(ajgl2009(), 8, kept=kept).block_plans(archs, z2)
    other_model, _ = PlanCache(dataclasses.replace(ajgl2009(), dt=2.0), 8, kept=kept).block_plans(
        archs, z1
    )
    after, _ = PlanCache(ajgl2009(), 8).block_plans(archs, z1)
    for a in archs:
        assert again[a] is first[a]
        assert other[a] is not first[a] and other_model[a] is not first[a]
        assert after[a] is not first[a]  # nothing is kept for a cache not given it
        # each block's plan is that of its own masks: its reported covariances
        np.testing.assert_array_equal(other[a].reported_cov, after_plan(a, z2).reported_cov)


def after_plan(arch: str, z: np.ndarray):
    return PlanCache(ajgl2009(), 8).block_plans([arch], z)[0][arch]


def test_run_summary_is_the_stages_one_by_one(tmp_path: Path):
    ok("run", DROPOUT, "--runs", "300", "--out-dir", tmp_path / "run")
    s, e = tmp_path / "run" / "sensors.mcap", tmp_path / "e.mcap"
    ok("estimate", s, "-o", e)
    ok("evaluate", s, e, "-o", tmp_path / "ev.rrd", "--summary", tmp_path / "summary.json")
    run = json.loads((tmp_path / "run" / "summary.json").read_text())
    stages = json.loads((tmp_path / "summary.json").read_text())
    assert run["architectures"] == stages["architectures"]
    assert all("expected" in v for v in run["architectures"].values())
