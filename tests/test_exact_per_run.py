"""Exact analysis of per-run plans (runs with their own measurement patterns, e.g. dropouts):
each run's statistics against the shared analysis of its pattern, their run average against
Monte Carlo, and the conditional expected values of `fusionlog run` on a dropout scenario."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conditioning import Sensitivity, assert_agree, sensitivity
from conftest import random_spd, random_system

from fusionlog.cli import main
from fusionlog.core.architectures import build_plan, estimate
from fusionlog.core.exact import (
    ConditionalExpected,
    analyse,
    expected_sqrt_quadratic,
    expected_sqrt_quadratic_many,
    plan_of_runs,
)
from fusionlog.core.metrics import MetricsAccumulator
from fusionlog.core.model import ajgl2009
from fusionlog.core.names import STATE_ARCHITECTURES
from fusionlog.core.quadratic_form import nees_and_dm_many
from fusionlog.core.simulate import simulate
from fusionlog.core.timing import SensorTiming
from fusionlog.errors import NumericalError
from fusionlog.io.mcap import McapFile
from fusionlog.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ("mse", "bias", "P", "nees", "dm")


def assert_same(per_run, r, shared, tol, sens: Sensitivity | None = None):
    """Run r of a per-run analysis equals a shared one: the same undefined entries (NaN), the
    others to `tol` relative to the largest entry of the field. With `sens` (the shared
    analysis' sensitivity to rounding), each field's tolerance is at least what rounding can
    move it by, and entries whose definedness rounding decides may differ in definedness."""
    for f in FIELDS:
        t = tol if sens is None else max(tol, sens.tolerance(f))
        unsettled = None if sens is None else sens.unsettled
        assert_agree(getattr(per_run, f)[r], getattr(shared, f), t, unsettled, f)


def build_gap(per_run_plan, r, shared_plan) -> float:
    """How far the builders' per-run and shared paths put two plans of the same pattern: the
    largest difference of their reported covariances (and of CI's weights), relative to the
    largest entry. About 1e-16 as a rule; more where the builds themselves differ (CI's
    weights are found by an iteration run per run; the first information inversions of a
    filter without a prior)."""
    P, Q = per_run_plan.reported_cov[r], shared_plan.reported_cov
    ok = np.isfinite(Q)
    gap = np.abs(P[ok] - Q[ok]).max(initial=0.0) / np.abs(Q[ok]).max(initial=1e-300)
    if per_run_plan.omega is not None:
        w, v = per_run_plan.omega[r], shared_plan.omega
        fin = np.isfinite(v)
        gap = max(gap, np.abs(w[fin] - v[fin]).max(initial=0.0))
    return float(gap)


def tolerance(per_run_plan, r, shared_plan) -> float:
    """1e-12, or 100 times the builders' own disagreement where that is larger."""
    return max(1e-12, 100.0 * build_gap(per_run_plan, r, shared_plan))


def shared_sensitivity(system, arch, K, mask=None) -> Sensitivity:
    """How far rounding moves the shared analysis of `mask` (`conditioning.sensitivity`)."""
    return sensitivity(lambda s: analyse(build_plan(s, arch, K, mask), s), system, FIELDS)


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_all_present_per_run_equals_shared(arch):
    """(a) A per-run plan whose mask has every measurement gives each run the shared numbers."""
    rng = np.random.default_rng(31)
    for system in (ajgl2009(), random_system(rng, 3, [1, 2, 1])):
        K = 12
        plan = build_plan(system, arch, K, np.ones((3, K + 1, system.m), bool))
        per_run = analyse(plan, system)
        assert per_run.nees.shape == (3, K + 1)
        assert per_run.mse.shape == (3, K + 1, system.n, system.n)
        shared_plan = build_plan(system, arch, K)
        shared = analyse(shared_plan, system)
        sens = shared_sensitivity(system, arch, K)
        for r in range(3):
            assert_same(per_run, r, analyse(plan_of_runs(plan, r), system), 1e-12)
            assert_same(per_run, r, shared, tolerance(plan, r, shared_plan), sens)


@pytest.mark.parametrize("prior", [True, False], ids=["prior", "no-prior"])
@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_each_run_equals_the_shared_analysis_of_its_pattern(arch, prior):
    """(b) Run r of a per-run analysis is the shared analysis of run r's pattern.

    Against the same maps (run r's cut out of the per-run plan) to 1e-12. Against a shared plan
    built anew from run r's mask to 1e-12 as well, unless the builders' per-run and shared
    paths put the two plans further apart than that themselves (`tolerance`).
    """
    rng = np.random.default_rng(7 if prior else 8)
    for trial in range(2):
        system = random_system(rng, 3, [1, 2, 1], prior=prior, correlated=trial == 1)
        M, K = 4, 8
        masks = rng.random((M, K + 1, system.m)) > 0.3
        masks[0] = True
        plan = build_plan(system, arch, K, masks)
        per_run = analyse(plan, system)
        for r in range(M):
            own = plan_of_runs(plan, r)
            assert not own.per_run
            assert_same(per_run, r, analyse(own, system), 1e-12)
            shared_plan = build_plan(system, arch, K, masks[r])
            anew = analyse(shared_plan, system)
            sens = shared_sensitivity(system, arch, K, masks[r])
            assert_same(per_run, r, anew, tolerance(plan, r, shared_plan), sens)


@pytest.mark.parametrize("arch", ["CKF", "MSC", "CI", "FBS"])
def test_irregular_instants_with_dropouts(arch):
    """A time-varying system (the multirate scenario's irregular instants, F and Q per
    interval) with per-run losses on top of its schedule: still each run's shared analysis."""
    sc = load_scenario(ROOT / "pipeline" / "multirate.toml")
    system = sc.system.on_times(sc.schedule.times)
    assert system.Fs is not None
    K = 30
    system = system.on_times(sc.schedule.times[: K + 1])
    sched = np.repeat(sc.schedule.measures[: K + 1], [s.dim for s in system.sensors], axis=1)
    rng = np.random.default_rng(3)
    masks = sched & (rng.random((3, K + 1, system.m)) > 0.2)
    plan = build_plan(system, arch, K, masks)
    per_run = analyse(plan, system)
    for r in range(3):
        assert_same(per_run, r, analyse(plan_of_runs(plan, r), system), 1e-12)
        shared_plan = build_plan(system, arch, K, masks[r])
        assert_same(per_run, r, analyse(shared_plan, system), tolerance(plan, r, shared_plan))


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC-GMF", "FBS"])
def test_measurement_noise_per_instant(arch):
    """A measurement noise covariance that varies per instant (`System.Rs`): the analysis takes
    the truth's at each step, so a filter optimal for its data reports its true covariance,
    run by run."""
    rng = np.random.default_rng(17)
    base = random_system(rng, 2, [1, 2])
    K = 10
    Rs = np.zeros((K + 1, base.m, base.m))
    for sl in base.sensor_slices:  # independent sensors (HKF is optimal only for those)
        d = sl.stop - sl.start
        Rs[:, sl, sl] = [random_spd(rng, d, s) for s in np.exp(rng.uniform(-2, 2, K + 1))]
    system = dataclasses.replace(base, Rs=Rs)
    masks = rng.random((5, K + 1, system.m)) > 0.3
    ex = analyse(build_plan(system, arch, K, masks), system)
    ok = ex.defined
    np.testing.assert_allclose(ex.mse[ok], ex.P[ok], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(ex.nees[ok], 2.0, rtol=1e-9)


def test_chunks_of_runs_give_the_same_numbers():
    system = ajgl2009()
    masks = np.random.default_rng(5).random((7, 11, 3)) > 0.2
    plan = build_plan(system, "MSC-GMF", 10, masks)
    whole, chunked = analyse(plan, system), analyse(plan, system, chunk_runs=3)
    for f in FIELDS:
        np.testing.assert_allclose(getattr(chunked, f), getattr(whole, f), rtol=1e-13, atol=0)


@pytest.mark.parametrize("arch", ["CKF", "MSC-GMF"])
def test_maps_per_measurement_history_are_given_to_their_runs(arch):
    """A per-run plan may hold a step's maps once per distinct measurement history, with each
    run's node at every step (`nodes`): the analysis gives each run its node's maps."""
    system = ajgl2009()
    rng = np.random.default_rng(12)
    masks = rng.random((4, 9, 3)) > 0.3
    masks = masks[[0, 1, 0, 2, 3, 1]]  # runs sharing their whole history
    masks[5, 6:] = True  # and one sharing only the first steps
    plan = build_plan(system, arch, 8, masks)
    nodes, steps = [], []
    for k, st in enumerate(plan.steps):
        hist = masks[:, : k + 1].reshape(len(masks), -1)
        _, first, index = np.unique(hist, axis=0, return_index=True, return_inverse=True)
        nodes.append(index.ravel())

        def per_node(a, first=first):
            if hasattr(a, "blocks"):
                return dataclasses.replace(a, blocks=a.blocks[first]) if a.ndim == 3 else a
            return a[first] if a is not None and a.ndim == 3 else a

        maps = {f: per_node(getattr(st, f)) for f in ("T", "U", "O", "P", "D")}
        steps.append(dataclasses.replace(st, **maps))
    assert len(np.unique(nodes[-1])) == 5
    on_nodes = dataclasses.replace(plan, steps=steps)
    on_nodes.nodes = nodes
    want = analyse(plan, system)
    got = analyse(on_nodes, system, chunk_runs=4)
    for f in FIELDS:
        np.testing.assert_allclose(getattr(got, f), getattr(want, f), rtol=1e-13, atol=0)


def test_a_failing_run_is_named():
    system = ajgl2009()
    masks = np.random.default_rng(6).random((5, 9, 3)) > 0.2
    plan = build_plan(system, "CKF", 8, masks)
    step = plan.steps[4]
    P = step.P.copy()
    P[3] = [[1.0, 2.0], [2.0, 1.0]]  # not positive definite
    plan.steps[4] = dataclasses.replace(step, P=P)
    with pytest.raises(NumericalError, match=r"architecture CKF, exact analysis, step 4 of run 3"):
        analyse(plan, system, chunk_runs=2)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_many_agrees_with_the_fixed_grid(n):
    """The batch routines (closed forms for n = 1 and for n = 2 without a mean, a fitted grid
    otherwise) against the 1601-node trapezoid of the shared analysis: means, no means,
    eigenvalues spread widely. The fixed grid stops at t = e^-60, which leaves out about
    2 E[q] e^-30 / (2 sqrt(pi)) of the integral: within that, 1e-12."""
    rng = np.random.default_rng(n)
    N = 300
    P = np.stack([random_spd(rng, n, s) for s in np.exp(rng.uniform(-4, 4, N))])
    C = np.stack([random_spd(rng, n, s) for s in np.exp(rng.uniform(-3, 3, N))])
    mean = rng.standard_normal((N, n)) * np.exp(rng.uniform(-3, 2, (N, 1)))
    mean[::2] = 0.0
    mse = C + mean[:, :, None] * mean[:, None, :]
    nees_want = np.einsum("kij,kji->k", np.linalg.inv(P), mse)  # E[q]
    want = expected_sqrt_quadratic(P, mean, C)
    tol = 1e-12 * want + 6e-14 * (nees_want + 1.0)
    assert (np.abs(expected_sqrt_quadratic_many(P, mean, C) - want) <= tol).all()
    nees, dm, good = nees_and_dm_many(P, mean, mse)
    assert good.all()
    assert (np.abs(dm - want) <= tol).all()
    np.testing.assert_allclose(nees, nees_want, rtol=1e-12)


def test_closed_forms():
    """n = 1: the folded normal mean; n = 2 without a mean: sqrt(2 l1 / pi) E(1 - l2 / l1)."""
    from scipy import special, stats

    for mu, sd in ((0.0, 1.0), (0.7, 0.3), (-5.0, 0.01), (2.0, 0.0)):
        P, C = np.array([[[4.0]]]), np.array([[[sd * sd]]])
        want = 0.5 * (abs(mu) if sd == 0 else stats.foldnorm(abs(mu) / sd, scale=sd).mean())
        assert nees_and_dm_many(P, np.array([[mu]]), C + mu * mu)[1][0] == pytest.approx(
            want, rel=1e-14
        )
    l1, l2 = 3.0, 0.25
    got = nees_and_dm_many(np.eye(2)[None], np.zeros((1, 2)), np.diag([l2, l1])[None])[1][0]
    assert got == pytest.approx(np.sqrt(2 * l1 / np.pi) * special.ellipe(1 - l2 / l1), rel=1e-15)


def test_many_marks_indefinite_covariances():
    P = np.array([[[1.0, 0.0], [0.0, 1.0]], [[1.0, 2.0], [2.0, 1.0]], [[np.nan] * 2] * 2])
    nees, dm, good = nees_and_dm_many(P, np.zeros((3, 2)), np.stack([np.eye(2)] * 3))
    assert good.tolist() == [True, False, False]
    assert nees[0] == pytest.approx(2.0, rel=1e-15) and np.isnan(nees[1:]).all()
    assert dm[0] == pytest.approx(np.sqrt(np.pi / 2), rel=1e-14) and np.isnan(dm[1:]).all()


def _dropouts(system, p):
    return dataclasses.replace(
        system,
        sensors=tuple(
            dataclasses.replace(s, timing=SensorTiming(dropout=p)) for s in system.sensors
        ),
    )


@pytest.fixture(scope="module")
def paper_dropouts():
    system = _dropouts(ajgl2009(), 0.1)
    x, z = simulate(system, 20, 2009, 0, 10_000)
    assert 0.08 < np.isnan(z).mean() < 0.12
    return system, x, z


@pytest.mark.parametrize("arch", [a for a in STATE_ARCHITECTURES if a != "CI"])
def test_conditional_expected_values_agree_with_monte_carlo(paper_dropouts, arch):
    """(c) The paper example with 10 % dropouts: the run average of the exact values given
    each run's pattern against the Monte Carlo MSE, ANEES and DM of the same runs (metrics
    module, its standard errors), within 4 standard errors."""
    system, x, z = paper_dropouts
    est = estimate(system, z, arch)
    acc = MetricsAccumulator(21, 2)
    acc.add(x, est.mean, est.cov)
    mc = acc.finalize()
    cond = ConditionalExpected(21, 2)
    cond.add(analyse(build_plan(system, arch, 20, ~np.isnan(z)), system))
    assert cond.runs == 10_000 and (cond.count == acc.count).all()
    exact = mc.expected_overall(cond.mse_per_state, cond.nees, cond.dm)
    for key, value, se in (
        ("mse", mc.mse, mc.stderr_mse),
        ("anees", mc.anees, mc.stderr_anees),
        ("dm", mc.dm, mc.stderr_dm),
    ):
        assert abs(value - exact[key]) < 4 * se, (arch, key, value, exact[key], se)
    # the pattern matters: more error than without losses
    assert exact["mse"] > analyse(build_plan(system, arch, 20), system).mse_per_state.mean()


def test_conditional_average_leaves_out_undefined_estimates_as_the_metrics_do():
    """Without a prior a run's estimate is undefined until its data make the state
    observable, which depends on its pattern: both averages count the same runs per step."""
    rng = np.random.default_rng(9)
    system = _dropouts(random_system(rng, 2, [1, 1], prior=False), 0.4)
    x, z = simulate(system, 10, 1, 0, 300)
    est = estimate(system, z, "MSC")
    acc = MetricsAccumulator(11, 2)
    acc.add(x, est.mean, est.cov)
    ex = analyse(build_plan(system, "MSC", 10, ~np.isnan(z)), system)
    cond = ConditionalExpected(11, 2)
    cond.add(ex)
    assert acc.count[0] < 300 and (cond.count == acc.count).all()
    k = int(np.argmax((acc.count > 0) & (acc.count < 300)))
    defined = np.isfinite(est.cov[:, k]).all(axis=(-2, -1))
    assert cond.nees[k] == pytest.approx(ex.nees[defined, k].mean(), rel=1e-12)
    # a shared plan counts as `runs` runs of its pattern
    shared = ConditionalExpected(11, 2)
    shared.add(analyse(build_plan(system, "MSC", 10), system), runs=5)
    assert shared.runs == 5 and shared.count.max() == 5


@pytest.fixture(scope="module")
def dropout_run(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("dropout") / "run"
    args = ["run", str(ROOT / "pipeline" / "ajgl2009_dropout.toml"), "--runs", "400"]
    args += ["--arch", "CKF", "--arch", "MSC", "--arch", "FBS", "--out-dir", str(d)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    return d


def test_run_reports_conditional_expected_values(dropout_run):
    """(d) `fusionlog run` on the dropout scenario: expected values present, marked
    conditional, within 4 standard errors of the Monte Carlo values."""
    summary = json.loads((dropout_run / "summary.json").read_text())
    assert list(summary["architectures"]) == ["CKF", "MSC", "FBS"]
    for arch, a in summary["architectures"].items():
        ex, se = a["expected"], a["stderr"]
        assert ex["conditional"] is True
        for key in ("mse", "anees", "dm"):
            assert ex[key] is not None
            assert abs(a[key] - ex[key]) < 4 * se[key], (arch, key, a[key], ex[key], se[key])
    assert summary["architectures"]["CKF"]["expected"]["anees"] == pytest.approx(2.0, rel=1e-9)
    assert summary["architectures"]["MSC"]["expected"]["anees"] > 3.5


def test_without_readings_there_are_no_conditional_values(dropout_run):
    """An evaluator fed blocks without their sensor readings (as a caller that only has the
    truth would) reports no expected values rather than the average of some runs."""
    from fusionlog.stages.common import open_evaluation_inputs
    from fusionlog.stages.kinds import kind_of

    sens, est, prov, sc = open_evaluation_inputs(
        dropout_run / "sensors.mcap", dropout_run / "estimates.mcap"
    )
    assert prov["measurement_pattern"] == "per-run"
    ev = kind_of(sc.kind).evaluator(sc, est, prov)
    assert ev.sensor_topics == ["/sensors/s1", "/sensors/s2", "/sensors/s3"]
    blocks = zip(
        sens.iter_run_blocks(["/truth"], 150), est.iter_run_blocks(ev.topics, 150), strict=True
    )
    for (off, _, tdata), (_, _, edata) in blocks:
        ev.add(off, tdata["/truth"], edata)
    for a in ev.summary()["architectures"].values():
        assert a["expected"] == {"mse": None, "anees": None, "dm": None}


def test_shared_patterns_are_not_marked(tmp_path):
    """Without dropouts `expected` is the unconditional analysis and has no `conditional` key
    (the golden summaries stay as they were)."""
    res = CliRunner().invoke(
        main,
        ["run", str(ROOT / "pipeline" / "ajgl2009.toml"), "--runs", "50", "--arch", "CKF"]
        + ["--out-dir", str(tmp_path / "r")],
    )
    assert res.exit_code == 0, res.output
    ex = json.loads((tmp_path / "r" / "summary.json").read_text())["architectures"]["CKF"]
    assert set(ex["expected"]) == {"mse", "anees", "dm"}
    assert McapFile(tmp_path / "r" / "estimates.mcap").runs() == 50
