"""Exact covariance analysis against closed forms and against Monte Carlo."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import random_spd, random_system
from scipy import special, stats

from fusionlog.core.architectures import build_plan, estimate
from fusionlog.core.exact import analyse, expected_sqrt_quadratic
from fusionlog.core.model import Prior, System, ajgl2009
from fusionlog.core.names import STATE_ARCHITECTURES
from fusionlog.core.simulate import simulate
from fusionlog.scenario import load_scenario


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_expected_dm_consistent_is_chi_mean(n):
    rng = np.random.default_rng(n)
    P = random_spd(rng, n)[None]
    chi_mean = np.sqrt(2) * special.gamma((n + 1) / 2) / special.gamma(n / 2)
    got = expected_sqrt_quadratic(P, np.zeros((1, n)), P)
    np.testing.assert_allclose(got, [chi_mean], rtol=1e-12)
    assert stats.chi(n).mean() == pytest.approx(chi_mean, rel=1e-12)


def test_expected_dm_general_gaussian_by_sampling():
    rng = np.random.default_rng(7)
    P, C = random_spd(rng, 3), random_spd(rng, 3, 2.0)
    mu = rng.standard_normal(3)
    got = expected_sqrt_quadratic(P[None], mu[None], C[None])[0]
    e = rng.multivariate_normal(mu, C, size=400_000)
    q = np.sqrt(np.einsum("ki,ij,kj->k", e, np.linalg.inv(P), e))
    assert abs(got - q.mean()) < 4 * q.std() / np.sqrt(q.size)


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC-GMF", "SKF", "FBS"])
def test_optimal_architectures_report_their_true_covariance(arch):
    """A filter (or smoother) optimal for its own data reports exactly its error covariance."""
    rng = np.random.default_rng(11)
    system = random_system(rng, 3, [1, 2, 1])
    ex = analyse(build_plan(system, arch, 30), system)
    np.testing.assert_allclose(ex.mse, ex.P, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(ex.nees, 3.0, rtol=1e-9)
    np.testing.assert_allclose(ex.bias, 0.0, atol=1e-12)


def _mc_stats(x, est):
    """Per-run averages (over steps) so that standard errors respect correlation in time."""
    err = x - est.mean
    P = est.cov
    nees = np.einsum("mki,kij,mkj->mk", err, np.linalg.inv(P), err)
    per_run = {
        "mse": (err**2).mean(axis=(1, 2)),
        "anees": nees.mean(axis=1),
        "dm": np.sqrt(nees).mean(axis=1),
    }
    return {k: (v.mean(), v.std(ddof=1) / np.sqrt(v.size)) for k, v in per_run.items()}


@pytest.fixture(scope="module")
def paper_mc():
    system = ajgl2009()
    x, z = simulate(system, 20, 2009, 0, 10_000)
    return system, x, z


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_monte_carlo_within_four_standard_errors_of_exact(paper_mc, arch):
    system, x, z = paper_mc
    mc = _mc_stats(x, estimate(system, z, arch))
    ex = analyse(build_plan(system, arch, 20), system)
    exact = {"mse": ex.mse_per_state.mean(), "anees": ex.nees.mean(), "dm": ex.dm.mean()}
    for key, (mean, se) in mc.items():
        assert abs(mean - exact[key]) < 4 * se, (key, mean, exact[key], se)


def test_paper_consistency_structure():
    system = ajgl2009()
    M, n = 10_000, 2
    upper = stats.chi2.ppf(0.975, M * n) / M
    ex = {a: analyse(build_plan(system, a, 20), system) for a in STATE_ARCHITECTURES}
    for a in ("CKF", "HKF", "MSC-GMF", "SKF", "FBS"):
        np.testing.assert_allclose(ex[a].nees, n, rtol=1e-9)
        np.testing.assert_allclose(ex[a].dm, np.sqrt(np.pi / 2), rtol=1e-9)
    # MSC ignores the common process noise: over-confident, far above the band.
    assert np.all(ex["MSC"].nees[1:] > 1.5 * upper)
    assert ex["MSC"].dm.mean() > 1.6
    # Equal MSE of MSC and MSC-GMF with identical sensors, CKF = HKF.
    np.testing.assert_allclose(ex["MSC"].mse, ex["MSC-GMF"].mse, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(ex["CKF"].mse, ex["HKF"].mse, rtol=1e-10, atol=1e-14)
    # CI is conservative: its reported covariance bounds the true one.
    d = ex["CI"].P - ex["CI"].mse
    assert np.linalg.eigvalsh(d).min() > -1e-12


def test_model_mismatch_against_monte_carlo():
    """A filter built on the wrong process noise and prior: exact analysis with the true model
    predicts the biased, inconsistent errors the simulation shows."""
    truth = ajgl2009()
    wrong = System(
        F=truth.F,
        Q=0.1 * truth.Q,
        sensors=truth.sensors,
        prior=Prior(np.array([99.0, -0.5]), 0.5 * np.eye(2)),
    )
    truth = System(
        F=truth.F, Q=truth.Q, sensors=truth.sensors, prior=truth.prior, initial=truth.prior
    )
    x, z = simulate(truth, 20, 5, 0, 20_000)
    for arch in ("CKF", "MSC", "FBS"):
        est = estimate(wrong, z, arch)
        ex = analyse(build_plan(wrong, arch, 20), truth)
        err = x - est.mean
        np.testing.assert_allclose(
            err.mean(axis=0), ex.bias, atol=4 * err.std(axis=0).max() / np.sqrt(len(x))
        )
        mc = _mc_stats(x, est)
        assert abs(mc["mse"][0] - ex.mse_per_state.mean()) < 4 * mc["mse"][1]
        assert abs(mc["anees"][0] - ex.nees.mean()) < 4 * mc["anees"][1]


def test_long_horizon_stays_accurate():
    """10^5 steps of a random walk: the truth's variance grows like k^3, the error's does not;
    the analysis must not lose the error in the cancellation."""
    system = ajgl2009()
    ex = analyse(build_plan(system, "MSC-GMF", 100_000), system)
    np.testing.assert_allclose(ex.nees, 2.0, rtol=1e-8)
    plan = build_plan(system, "CKF", 100_000)
    P = plan.reported_cov
    np.testing.assert_array_equal(P, np.swapaxes(P, 1, 2))
    assert np.linalg.eigvalsh(P).min() > 0


@pytest.mark.parametrize("arch", ["CKF", "MSC-GMF", "SKF", "FBS"])
def test_correlated_sensor_noise_is_accounted_for(arch):
    """With cross-covariances between sensor noises (block R of eq. 31), the CKF and the
    GMF's joint recursion (35) with the K_i R_ij K_j^T term stay exact: reported = true."""
    rng = np.random.default_rng(21)
    system = random_system(rng, 2, [1, 2, 1], correlated=True)
    assert system.cross_R
    ex = analyse(build_plan(system, arch, 25), system)
    np.testing.assert_allclose(ex.mse, ex.P, rtol=1e-8, atol=1e-12)


def test_hkf_ignores_sensor_correlation_and_pays_for_it():
    """HKF's equivalent measurements assume independent sensors: with correlated noise it is no
    longer the CKF, and the exact analysis shows it (true MSE above the CKF's)."""
    rng = np.random.default_rng(22)
    system = random_system(rng, 2, [1, 1], correlated=True)
    ckf = analyse(build_plan(system, "CKF", 25), system)
    hkf = analyse(build_plan(system, "HKF", 25), system)
    assert np.trace(hkf.mse[-1]) > np.trace(ckf.mse[-1]) * (1 + 1e-6)


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_hundred_thousand_steps_stay_symmetric_positive_definite(arch):
    system = ajgl2009()
    P = build_plan(system, arch, 100_000).reported_cov
    assert P.shape == (100_001, 2, 2)
    np.testing.assert_array_equal(P, np.swapaxes(P, 1, 2))
    assert np.linalg.eigvalsh(P).min() > 0


def _independent_msc_recursion(F, Q, H, R, P0, S, K):
    """Expected NEES and DM of MSC at k = 0..K, written out from the model alone (plain numpy,
    nothing of fusionlog's): S local KFs on identical sensors z_j = H x + v_j started from the
    common prior, their joint error covariance J propagated step by step (common prior error
    and process noise, independent measurement noises), Millman's fusion P = (sum P_j^-1)^-1
    with weights c_j = P P_j^-1, and its true error covariance M = C J C^T. Then
    NEES = tr(P^-1 M) and DM = E ||W e|| for e ~ N(0, M), W^T W = P^-1: with l1 >= l2 the
    eigenvalues of W M W^T (n = 2), E sqrt(l1 z1^2 + l2 z2^2) = E[r] E_theta sqrt(l1 cos^2 +
    l2 sin^2) = sqrt(pi / 2) (2 / pi) sqrt(l1) E(1 - l2 / l1), E the complete elliptic
    integral of the second kind."""
    n = F.shape[0]
    eye = np.eye(n)
    P = [P0.copy() for _ in range(S)]
    J = np.kron(np.ones((S, S)), P0)
    nees, dm = [], []
    for k in range(K + 1):
        if k > 0:
            P = [F @ Pj @ F.T + Q for Pj in P]
            Fs = np.kron(np.eye(S), F)
            J = Fs @ J @ Fs.T + np.kron(np.ones((S, S)), Q)
        gains = [Pj @ H.T @ np.linalg.inv(H @ Pj @ H.T + R) for Pj in P]
        A = np.zeros((S * n, S * n))
        B = np.zeros((S * n, S * R.shape[0]))
        for j, Kj in enumerate(gains):
            A[j * n : (j + 1) * n, j * n : (j + 1) * n] = eye - Kj @ H
            B[j * n : (j + 1) * n, j * R.shape[0] : (j + 1) * R.shape[0]] = Kj
        J = A @ J @ A.T + B @ np.kron(np.eye(S), R) @ B.T
        P = [(eye - Kj @ H) @ Pj for Kj, Pj in zip(gains, P, strict=True)]
        Pf = np.linalg.inv(sum(np.linalg.inv(Pj) for Pj in P))
        C = np.hstack([Pf @ np.linalg.inv(Pj) for Pj in P])
        M = C @ J @ C.T
        nees.append(np.trace(np.linalg.solve(Pf, M)))
        Lc = np.linalg.cholesky(Pf)
        lam = np.linalg.eigvalsh(np.linalg.solve(Lc, np.linalg.solve(Lc, M).T))
        chi = (
            np.sqrt(np.pi / 2) * 2 / np.pi * np.sqrt(lam[-1]) * special.ellipe(1 - lam[0] / lam[-1])
        )
        dm.append(chi)
    return np.array(nees), np.array(dm)


def test_msc_paper_anees_and_dm_pinned_by_an_independent_joint_recursion():
    """The paper example (pipeline/ajgl2009.toml, K = 20): MSC's expected ANEES 3.8715 and DM
    1.7286, pinned by a recursion written in this test from F, Q, H, R and the prior, and
    exact.analyse agrees with it step by step. (A 21 % error in MSC's covariance passed the
    one-sided bounds of test_paper_consistency_structure.)"""
    sc = load_scenario(Path(__file__).resolve().parents[1] / "pipeline" / "ajgl2009.toml")
    system = sc.system
    assert sc.steps == 20 and len(system.sensors) == 3
    s0 = system.sensors[0]
    assert all(np.array_equal(s.H, s0.H) and np.array_equal(s.R, s0.R) for s in system.sensors)
    assert not system.cross_R and system.G is None
    nees, dm = _independent_msc_recursion(
        system.F, system.Q, s0.H, s0.R, system.prior.cov, len(system.sensors), sc.steps
    )
    assert nees.mean() == pytest.approx(3.8715, abs=1e-4)
    assert dm.mean() == pytest.approx(1.7286, abs=1e-4)
    ex = analyse(build_plan(system, "MSC", sc.steps), system)
    np.testing.assert_allclose(ex.nees, nees, rtol=1e-9)
    np.testing.assert_allclose(ex.dm, dm, rtol=1e-7)
    assert ex.nees.mean() == pytest.approx(3.8715, abs=1e-4)
    assert ex.dm.mean() == pytest.approx(1.7286, abs=1e-4)
