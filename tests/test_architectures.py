"""Filters and architectures: identities the theory promises, and the two execution paths."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_spd, random_system

from fusionlog.core import names
from fusionlog.core.architectures import (
    REGISTRY,
    STATE_ARCHITECTURES,
    STEADY_BLOCK,
    build_plan,
    estimate,
    parse_arch,
    run_plan,
)
from fusionlog.core.exact import analyse
from fusionlog.core.fusion import ci_omega
from fusionlog.core.kalman import update_joseph, update_millman
from fusionlog.core.model import Prior, Sensor, System, ajgl2009
from fusionlog.core.simulate import simulate


def test_kf_update_joseph_equals_millman_form():
    """Eq. (14)+(18) against eqs. (19)-(24): the update is Millman fusion with the ML estimate."""
    rng = np.random.default_rng(0)
    for n, m in [(1, 1), (2, 1), (3, 2), (4, 4)]:
        P = random_spd(rng, n)
        H = rng.standard_normal((m, n))
        R = random_spd(rng, m)
        x = rng.standard_normal((5, n))
        z = rng.standard_normal((5, m))
        xj, Pj = update_joseph(x, P, z, H, R)
        xm, Pm = update_millman(x, P, z, H, R)
        np.testing.assert_allclose(xj, xm, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(Pj, Pm, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_hkf_equals_ckf(seed):
    """Eqs. (36)-(40) reproduce the centralised KF (29)-(31), heterogeneous sensors included."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 5))
    dims = [int(d) for d in rng.integers(1, 4, size=int(rng.integers(1, 6)))]
    system = random_system(rng, n, dims)
    _, z = simulate(system, 25, seed, 0, 4)
    ckf, hkf = estimate(system, z, "CKF"), estimate(system, z, "HKF")
    scale = np.abs(ckf.mean).max()
    np.testing.assert_allclose(hkf.mean, ckf.mean, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(hkf.cov, ckf.cov, rtol=1e-9, atol=1e-12)


def test_paper_structure_ckf_hkf_and_msc_gmf():
    system = ajgl2009()
    x, z = simulate(system, 20, 1, 0, 500)
    ests = {a: estimate(system, z, a) for a in STATE_ARCHITECTURES}
    np.testing.assert_allclose(ests["HKF"].mean, ests["CKF"].mean, atol=1e-9)
    # Identical sensors: the optimal GMF weights are the plain average, as are Millman's.
    np.testing.assert_allclose(ests["MSC-GMF"].mean, ests["MSC"].mean, atol=1e-9)
    # ... but MSC claims a covariance the errors do not have (over-confidence).
    assert np.all(
        np.trace(ests["MSC"].cov, axis1=1, axis2=2)[1:]
        < np.trace(ests["MSC-GMF"].cov, axis1=1, axis2=2)[1:]
    )
    # The smoother never reports more uncertainty than the filter.
    d = ests["CKF"].cov - ests["FBS"].cov
    assert np.all(np.linalg.eigvalsh(d) > -1e-12)
    np.testing.assert_allclose(ests["FBS"].mean[:, -1], ests["CKF"].mean[:, -1], atol=1e-9)


def _tol(arch: str) -> float:
    """CI's omegas come out of a numerical optimiser (SLSQP, several steps or runs per call),
    accurate to about 1e-8: paths that group the problems differently agree to that, not to
    rounding. Every other architecture is a closed-form computation."""
    return 1e-6 if arch == "CI" else 1e-9


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_per_run_path_equals_shared_path(arch):
    """The batched per-run path with nothing missing gives the shared-gain numbers."""
    rng = np.random.default_rng(1)
    system = random_system(rng, 3, [1, 2, 1])
    _, z = simulate(system, 12, 3, 0, 5)
    shared = run_plan(build_plan(system, arch, 12), z)
    per_run = run_plan(build_plan(system, arch, 12, np.ones(z.shape, bool)), z)
    assert per_run.cov.ndim == 4 and shared.cov.ndim == 3
    np.testing.assert_allclose(per_run.mean, shared.mean, rtol=_tol(arch), atol=_tol(arch) / 10)
    np.testing.assert_allclose(
        per_run.cov, np.broadcast_to(shared.cov, per_run.cov.shape), rtol=_tol(arch), atol=1e-12
    )


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_missing_measurements_per_run(arch):
    """Runs with different NaN patterns: each run equals a shared plan built for its own mask,
    which in turn equals dropping the missing sensor from that step."""
    rng = np.random.default_rng(2)
    system = random_system(rng, 2, [1, 1, 2])
    _, z = simulate(system, 10, 4, 0, 4)
    z = z.copy()
    z[0, 3, 0] = np.nan
    z[1, 5:7, 1] = np.nan
    z[2, 0, 2:4] = np.nan
    z[3, 8, 3] = np.nan  # one component of a 2-D sensor
    est = estimate(system, z, arch)
    assert est.cov.ndim == 4
    for r in range(z.shape[0]):
        mask = ~np.isnan(z[r])
        single = run_plan(build_plan(system, arch, 10, mask), z[r : r + 1])
        np.testing.assert_allclose(
            est.mean[r], single.mean[0], rtol=_tol(arch), atol=_tol(arch) / 10
        )
        np.testing.assert_allclose(est.cov[r], single.cov, rtol=_tol(arch), atol=1e-12)


@pytest.mark.parametrize("per_run", [False, True])
def test_identical_sensors_with_different_gaps_keep_their_own_history(per_run):
    """Local filters of identical sensors that missed different measurements have different
    covariances from then on, even when their sensors report together again: MSC's P is
    Millman's fusion, eq. (33), of the single-sensor filters run with the same mask."""
    system = ajgl2009()
    K = 12
    present = np.ones((K + 1, 3), dtype=bool)
    present[0, 1] = False
    present[3:5, 0] = False
    if per_run:
        present = np.stack([present, np.ones_like(present), present[:, ::-1]])
    msc = build_plan(system, "MSC", K, present).reported_cov
    local = [build_plan(system, f"SKF:s{j + 1}", K, present).reported_cov for j in range(3)]
    millman = np.linalg.inv(sum(np.linalg.inv(P) for P in local))
    np.testing.assert_allclose(msc, millman, rtol=1e-12, atol=1e-14)


def test_missing_sensor_equals_filter_without_it():
    rng = np.random.default_rng(3)
    system = random_system(rng, 2, [1, 1])
    _, z = simulate(system, 6, 5, 0, 1)
    zz = z.copy()
    zz[:, :, 1] = np.nan
    only_first = estimate(system, zz, "CKF")
    skf = estimate(system, z, "SKF:s1")
    np.testing.assert_allclose(only_first.mean, skf.mean, atol=1e-10)
    assert only_first.cov.ndim == 3  # the same pattern in every run keeps the shared path
    np.testing.assert_allclose(only_first.cov, skf.cov, atol=1e-12)


def _static_two_sensor_system(prior: bool) -> System:
    """Gustafsson-Hendeby's triangulation: x = (1, 1), two position estimates with H = I."""
    R1 = 0.1 * np.array([[1.0, -0.8], [-0.8, 1.0]])
    R2 = 0.1 * np.array([[1.0, 0.8], [0.8, 1.0]])
    return System(
        F=np.eye(2),
        Q=np.zeros((2, 2)),
        sensors=(Sensor("a", np.eye(2), R1), Sensor("b", np.eye(2), R2)),
        prior=Prior(np.zeros(2), 1e12 * np.eye(2)) if prior else None,
        initial=Prior(np.ones(2), np.zeros((2, 2))),
    )


def test_no_prior_information_form_is_wls():
    """Without a prior the first estimate is exactly the WLS / fusion formula of the slides."""
    system = _static_two_sensor_system(prior=False)
    _, z = simulate(system, 0, 1, 0, 50)
    R1, R2 = system.sensors[0].R, system.sensors[1].R
    P = np.linalg.inv(np.linalg.inv(R1) + np.linalg.inv(R2))
    x = (np.linalg.solve(R1, z[:, 0, :2].T) + np.linalg.solve(R2, z[:, 0, 2:].T)).T @ P
    np.testing.assert_allclose(P, np.diag([0.018, 0.018]), atol=1e-15)
    for arch in ("CKF", "HKF", "MSC", "MSC-GMF", "FBS"):
        est = estimate(system, z, arch)
        np.testing.assert_allclose(est.cov[0], P, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(est.mean[:, 0], x, rtol=1e-12, atol=1e-12)


def test_no_prior_unobservable_then_defined():
    """Position-only sensors on a constant-velocity state: undefined at k = 0, exact after, and
    the limit of an ever vaguer prior."""
    system0 = ajgl2009()
    system = System(
        F=system0.F, Q=system0.Q, sensors=system0.sensors, prior=None, initial=system0.prior
    )
    vague = System(
        F=system0.F,
        Q=system0.Q,
        sensors=system0.sensors,
        prior=Prior(np.zeros(2), 1e7 * np.eye(2)),
        initial=system0.prior,
    )
    _, z = simulate(system, 8, 2, 0, 3)
    for arch in ("CKF", "HKF", "MSC", "FBS", "SKF"):
        est = estimate(system, z, arch)
        ref = estimate(vague, z, arch)
        assert np.isnan(est.cov[0]).all() and np.isnan(est.mean[:, 0]).all() or arch == "FBS"
        np.testing.assert_allclose(est.mean[:, 1:], ref.mean[:, 1:], rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(est.cov[1:], ref.cov[1:], rtol=1e-5, atol=1e-5)


def _assert_spd(P: np.ndarray) -> None:
    assert np.isfinite(P).all()
    np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    assert np.linalg.eigvalsh(P).min() > 0


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_extreme_noise_scales(arch):
    """R spanning 1e-8 .. 1e8 breaks no architecture."""
    system0 = ajgl2009()
    sensors = tuple(
        Sensor(f"s{j}", np.array([[1.0, 0.0]]), np.array([[r]]))
        for j, r in enumerate([1e-8, 1.0, 1e8])
    )
    system = System(F=system0.F, Q=system0.Q, sensors=sensors, prior=system0.prior)
    x, z = simulate(system, 30, 1, 0, 200)
    est = estimate(system, z, arch)
    _assert_spd(est.cov)
    assert np.isfinite(est.mean).all()
    err = x - est.mean
    nees = np.einsum("mki,kij,mkj->mk", err, np.linalg.inv(est.cov), err)
    assert nees.mean() < (10.0 if arch != "MSC" else 100.0)


def test_dense_path_keeps_precision_with_a_large_prior_mean():
    """UTM-sized coordinates: the dense map must not cancel the gains against the prior mean."""
    system0 = ajgl2009()
    system = System(
        F=system0.F,
        Q=system0.Q,
        sensors=system0.sensors,
        prior=Prior(np.array([5e6, -1.0]), np.eye(2)),
    )
    _, z = simulate(system, 100, 1, 0, 50)
    plan = build_plan(system, "CKF", 100)
    dense, steps = run_plan(plan, z).mean, run_plan(plan, z, route="steps").mean
    np.testing.assert_allclose(dense, steps, rtol=1e-13, atol=1e-7)


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
@pytest.mark.parametrize("prior", [True, False])
def test_steady_tail_in_blocks_equals_step_recursion(arch, prior):
    """A long log with few runs runs its steady tail (and FBS's steady middle) in blocks of
    steps; the numbers are those of the plain step recursion, also far from the origin."""
    system0 = ajgl2009()  # every local filter observable: all plans reach a steady state
    far = Prior(np.array([5e4, -1.0]), np.eye(2))
    system = System(
        F=system0.F,
        Q=system0.Q,
        sensors=system0.sensors,
        prior=far if prior else None,
        initial=None if prior else far,
    )
    K = 1000 + 7  # not a multiple of the block
    _, z = simulate(system, K, 2, 3, 50)
    plan = build_plan(system, arch, K)
    assert plan.steady_from < K + 1 - 2 * STEADY_BLOCK  # the blocked path runs
    blocked = run_plan(plan, z).mean
    stepwise = run_plan(plan, z, route="steps").mean
    np.testing.assert_allclose(blocked, stepwise, rtol=1e-11, atol=1e-9)


def _position_and_velocity_sensors(prior: bool) -> System:
    system0 = ajgl2009()
    sensors = (
        Sensor("pos", np.array([[1.0, 0.0]]), np.array([[1.0]])),
        Sensor("vel", np.array([[0.0, 1.0]]), np.array([[0.2]])),
    )
    return System(
        F=system0.F,
        Q=system0.Q,
        sensors=sensors,
        prior=system0.prior if prior else None,
        initial=system0.prior,
    )


@pytest.mark.parametrize("arch", ["MSC-GMF", "CI", "MSC"])
def test_track_to_track_without_prior_when_no_local_is_observable_alone(arch):
    """A position-only and a velocity-only local filter, no prior: neither has a mean of its
    own for a while, but together they determine the state from k = 0 on. The information-form
    GMF (constraint sum c_j D_j = I) and CI still fuse them."""
    system = _position_and_velocity_sensors(prior=False)
    x, z = simulate(system, 15, 3, 0, 4000)
    est = estimate(system, z, arch)
    assert np.isfinite(est.mean).all() and np.isfinite(est.cov).all()
    ex = analyse(build_plan(system, arch, 15), system)
    if arch == "MSC-GMF":
        np.testing.assert_allclose(ex.mse, ex.P, rtol=1e-8, atol=1e-12)  # optimal given J
    err = x - est.mean
    mse = (err**2).mean(axis=(0, 2))
    se = (err**2).mean(axis=2).std(axis=0) / np.sqrt(len(x))
    assert np.all(np.abs(mse - ex.mse_per_state.mean(axis=1)) < 5 * se)


@pytest.mark.parametrize("arch", ["MSC-GMF", "CI", "AVG", "MSC"])
def test_per_run_results_do_not_depend_on_other_runs(arch):
    """A run whose velocity sensor never reports must not make another run's estimate undefined
    (the block switches representation only when every run can; readouts are per run)."""
    system = _position_and_velocity_sensors(prior=False)
    _, z = simulate(system, 10, 4, 0, 2)
    z = z.copy()
    z[1, :, 1] = np.nan
    z[0, 3, 0] = np.nan  # make the patterns differ so the per-run path is taken
    both = estimate(system, z, arch)
    alone = estimate(system, z[:1], arch)
    tol = _tol(arch)
    np.testing.assert_allclose(both.mean[0], alone.mean[0], rtol=tol, atol=tol)
    if arch == "AVG":  # the velocity-only local never has a position: nothing to average
        assert np.isnan(both.mean[0]).all()
    else:
        assert np.isfinite(both.mean[0, 1:]).all()


@pytest.mark.parametrize("arch", ["CI", "MSC", "MSC-GMF", "HKF", "CKF", "FBS"])
def test_no_prior_run_that_sees_nothing_at_first(arch):
    """Without a prior, a run with no measurement at k = 0 has no estimate there (NaN), and
    once its information suffices, finite ones. CI once raised LinAlgError here: its fusion of
    no weights is NaN, and the invertibility test ran LAPACK's eigensolver on NaN."""
    system = random_system(np.random.default_rng(4), 3, [2, 2, 1], prior=False, correlated=True)
    K = 12
    present = np.ones((3, K + 1, system.m), bool)
    present[0, 2, 0] = False
    present[1, 4:7, system.m - 1] = False
    present[2, 0, :] = False
    present[2, 8, 1 % system.m] = False
    _, z = simulate(system, K, 5, 0, 3)
    z[~present] = np.nan
    e = estimate(system, z, arch)
    if arch != "FBS":  # the smoother has the later measurements at k = 0
        assert np.isnan(e.mean[2, 0]).all()
    assert np.isfinite(e.mean[:, -1]).all()


def test_registry_is_the_list_of_names():
    """One list: core.names takes its names and parse_arch from the registry (the default
    list: the registered architectures a scenario runs without its own list), every name has a
    plan, and only SKF takes a sensor."""
    default = tuple(a for a in REGISTRY if REGISTRY[a].default)
    assert names.STATE_ARCHITECTURES == STATE_ARCHITECTURES == default
    assert names.parse_arch is parse_arch
    assert set(names.PAPER_ARCHITECTURES) <= set(REGISTRY)
    assert [a.name for a in REGISTRY.values() if a.takes_sensor] == ["SKF"]
    system = ajgl2009()
    for name in REGISTRY:
        assert build_plan(system, name, 3).name == name
    with pytest.raises(ValueError, match="unknown architecture 'EKF'"):
        build_plan(system, "EKF", 3)
    with pytest.raises(ValueError, match="only SKF takes a sensor suffix"):
        parse_arch("CKF:s1", ["s1"])


def test_ci_plan_records_the_omega_of_every_step():
    """CI's typed `omega` field: per step, the covariance-intersection weights of the local
    filters' covariances (those of the SKF on each sensor)."""
    rng = np.random.default_rng(5)
    system = random_system(rng, 2, [1, 2, 1])
    K = 8
    plan = build_plan(system, "CI", K)
    assert plan.omega.shape == (K + 1, 3)
    assert build_plan(system, "MSC", K).omega is None
    local = [build_plan(system, f"SKF:{s.name}", K).reported_cov for s in system.sensors]
    for k in range(K + 1):
        om = ci_omega([P[k] for P in local])
        np.testing.assert_allclose(plan.omega[k], om, atol=1e-6)
        P = np.linalg.inv(sum(w * np.linalg.inv(Pj[k]) for w, Pj in zip(om, local, strict=True)))
        np.testing.assert_allclose(plan.reported_cov[k], P, rtol=1e-5)
