"""Every linear architecture against a per-run reference written from the paper's equations
(`references`), for the cases the FilterPy references do not reach: the track-to-track
architectures (MSC, MSC-GMF, CI, AVG) and HKF with correlated sensors, lost measurements and
irregular instants; no prior (the information form, the batch least squares of the smoother,
the best unbiased combination of the local information vectors); the paper's example where the
GMF system is singular; estimates that do not depend on the units of the states. Tolerances
come from the problem's own sensitivity to rounding (`conditioning`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conditioning import assert_agree, sensitivity
from conftest import random_system
from references import (
    K,
    basis_runs,
    data_of,
    estimate_ours,
    information_filter,
    mask_of,
    no_prior_reference,
    on_irregular_instants,
    reference,
    system_of,
)

from fusionlog.core.architectures import estimate
from fusionlog.core.model import Prior, System, ajgl2009

CASES = [
    # (architecture, sensor sizes, correlated, lost measurements)
    ("MSC", [1, 2, 1], True, True),
    ("MSC", [2, 1], False, True),
    ("MSC-GMF", [1, 2, 1], True, True),
    ("MSC-GMF", [2, 2], True, False),
    ("AVG", [1, 2, 1], True, True),
    ("AVG", [2, 1], False, False),
    ("CI", [2, 1], True, True),
    ("CI", [1, 2], False, False),
    ("HKF", [1, 2, 1], True, True),
    ("HKF", [2, 1], True, False),
]
IDS = [
    f"{a}-{'x'.join(map(str, d))}{'-corr' if c else ''}{'-lost' if lo else ''}"
    for a, d, c, lo in CASES
]


def assert_equals_reference(system: System, arch: str, z, mean, cov) -> None:
    """Ours equals the reference's means (runs last: (K+1, M, n)) and covariances to what
    rounding can move ours by (`conditioning.sensitivity`)."""
    compute = estimate_ours(arch, z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    assert_agree(got.mean, np.swapaxes(mean, 0, 1), sens.tolerance("mean"), sens.unsettled, arch)
    assert_agree(got.cov, cov, sens.tolerance("cov"), sens.unsettled, arch)


@pytest.mark.parametrize(("arch", "dims", "correlated", "lost"), CASES, ids=IDS)
def test_architecture_equals_its_equations_per_run(arch, dims, correlated, lost) -> None:
    """Means and reported covariances of every run equal the reference loop's."""
    system = system_of(31 + len(dims), dims, correlated)
    mask = mask_of(system, 5) if lost else np.ones((K + 1, system.m), bool)
    z = data_of(system, mask)
    mean, cov = reference(system, arch, z, mask)
    assert_equals_reference(system, arch, z, mean, cov)


@pytest.mark.parametrize("arch", ["MSC", "MSC-GMF", "CI", "AVG", "HKF"])
def test_architecture_equals_its_equations_on_irregular_instants(arch: str) -> None:
    """The same on irregular instants (a transition and a process noise per interval)."""
    dims = [2, 1] if arch == "CI" else [1, 2, 1]
    system = on_irregular_instants(system_of(61, dims), 2)
    mask = mask_of(system, 6)
    z = data_of(system, mask)
    mean, cov = reference(system, arch, z, mask)
    assert_equals_reference(system, arch, z, mean, cov)


def test_hkf_with_correlated_sensors_is_not_the_ckf() -> None:
    """The HKF case above is not the CKF in disguise: with correlated sensors they differ."""
    system = system_of(34, [1, 2, 1])
    mask = np.ones((K + 1, system.m), bool)
    z = data_of(system, mask)
    a, b = estimate(system, z, "HKF"), estimate(system, z, "CKF")
    assert np.abs(a.mean - b.mean).max() > 1e-3 * np.abs(b.mean).max()


# --------------------------------------------------------------------------------------------
# No prior: the information form


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC"])
@pytest.mark.parametrize(("dims", "lost"), [([1, 1, 1], False), ([1, 2], True)])
def test_no_prior_equals_the_information_form(arch: str, dims, lost: bool) -> None:
    """Without a prior, every step whose information is well conditioned (cond < 1e8) has the
    information filter's mean and covariance; ours reports no estimate only where the
    information is singular to working precision."""
    system = random_system(np.random.default_rng(50 + len(dims)), 3, dims, prior=False,
                           correlated=True)  # fmt: skip
    mask = mask_of(system, 11, 0.2) if lost else np.ones((K + 1, system.m), bool)
    z = data_of(system, mask)
    mean, cov, cond = no_prior_reference(system, arch, z, mask)
    compute = estimate_ours(arch, z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    undefined = np.isnan(got.cov).any(axis=(1, 2))
    assert (cond[undefined] > 1e8).all(), arch
    use = (cond < 1e8) & ~sens.unsettled
    assert use.sum() >= K - 2
    mean_ref = np.swapaxes(mean, 0, 1)
    assert_agree(got.mean[use], mean_ref[use], sens.tolerance("mean"), None, arch)
    assert_agree(got.cov[use], cov[use], sens.tolerance("cov"), None, arch)


@pytest.mark.parametrize("arch", ["MSC", "MSC-GMF", "CI", "AVG", "HKF", "FBS"])
def test_paper_example_equals_the_equations(arch: str) -> None:
    """The paper's example (ajgl2009: the locals share the prior and the process noise, so the
    generalised Millman system is singular; two sensors, where CI's reference is exact), with
    lost measurements."""
    system = ajgl2009(n_sensors=2)
    mask = np.ones((K + 1, system.m), bool)
    mask[np.random.default_rng(8).random(K + 1) < 0.3, 0] = False
    z = data_of(system, mask)
    mean, cov = reference(system, arch, z, mask)
    assert_equals_reference(system, arch, z, mean, cov)


# --------------------------------------------------------------------------------------------
# Units


def _in_units(system: System, d: np.ndarray) -> System:
    """The same system with its states in other units: x' = T x, T = diag(d)."""
    T, Ti = np.diag(d), np.diag(1 / d)
    sensors = tuple(dataclasses.replace(s, H=s.H @ Ti) for s in system.sensors)
    prior = Prior(T @ system.prior.mean, T @ system.prior.cov @ T)
    return dataclasses.replace(
        system, F=T @ system.F @ Ti, Q=T @ system.Q @ T, sensors=sensors, prior=prior, initial=None
    )


@pytest.mark.parametrize("arch", ["MSC-GMF", "CKF", "MSC", "AVG", "HKF", "FBS"])
def test_estimates_do_not_depend_on_the_units_of_the_states(arch: str) -> None:
    """States in other units (one in thousandths, one in ten-thousands of the first's): the
    estimates are the same ones in those units. The generalised Millman formula's optimum is
    invariant (its P is the smallest in the Loewner order, whatever the trace's weighting);
    solving its KKT system with one scale for the whole matrix cut the rank at a fixed share
    of the largest entry, so a state in small units lost its variance as if it were rounding:
    MSC-GMF's P moved by 1.5 % and 4.4 %, its trace 1.2 % and 8.8 % above the optimum."""
    system = system_of(3, [1, 2, 1])
    mask = mask_of(system, 4)
    z = data_of(system, mask)
    ref = estimate(system, z, arch)
    sens = sensitivity(estimate_ours(arch, z), system, ("mean", "cov"))
    for d in ([1e3, 1.0, 1e-3], [1e5, 1.0, 1e-4]):
        d = np.array(d)
        est = estimate(_in_units(system, d), z, arch)
        cov = est.cov if est.cov.ndim == 3 else est.cov[0]
        rcov = ref.cov if ref.cov.ndim == 3 else ref.cov[0]
        back_mean, back_cov = est.mean / d, cov / np.outer(d, d)
        assert_agree(np.swapaxes(back_mean, 0, 1), np.swapaxes(ref.mean, 0, 1),
                     sens.tolerance("mean", 1e-11), sens.unsettled, f"{arch} {d}")  # fmt: skip
        assert_agree(back_cov, rcov, sens.tolerance("cov", 1e-11), sens.unsettled, f"{arch} {d}")


# --------------------------------------------------------------------------------------------
# The smoother as one least-squares problem


def batch_smoother(system: System, z: np.ndarray, mask: np.ndarray):
    """The fixed-interval smoother as the weighted least squares over all states x_0..x_K:
    minimise sum_k |z_k - H x_k|^2_{R^-1} (present rows, full R with its cross-covariances) +
    sum_k |x_k - F_k x_{k-1}|^2_{Q_k^-1} (+ |x_0 - m_0|^2_{P_0^-1} with a prior). The smoothed
    means solve the normal equations, the covariances are the diagonal blocks of the inverse
    of their matrix (what FBS, eqs. 25-28, computes recursively)."""
    n, K1, M = system.n, z.shape[1], z.shape[0]
    N = n * K1
    A, b = np.zeros((N, N)), np.zeros((M, N))
    if system.prior is not None:
        Y0 = np.linalg.inv(system.prior.cov)
        A[:n, :n] += Y0
        b[:, :n] += Y0 @ system.prior.mean
    for k in range(1, K1):
        F, Qi = system.F_at(k), np.linalg.inv(system.GQG_at(k))
        B = np.zeros((n, N))  # x_k - F x_{k-1} = B x
        B[:, k * n : (k + 1) * n] = np.eye(n)
        B[:, (k - 1) * n : k * n] = -F
        A += B.T @ Qi @ B
    for k in range(K1):
        r = np.flatnonzero(mask[k])
        if r.size:
            H, Ri = system.H[r], np.linalg.inv(system.R[np.ix_(r, r)])
            A[k * n : (k + 1) * n, k * n : (k + 1) * n] += H.T @ Ri @ H
            b[:, k * n : (k + 1) * n] += z[:, k, r] @ Ri @ H
    cov_all = np.linalg.inv(A)
    mean = (b @ cov_all).reshape(M, K1, n)
    cov = np.array([cov_all[k * n : (k + 1) * n, k * n : (k + 1) * n] for k in range(K1)])
    return mean, cov, np.linalg.cond(A)


@pytest.mark.parametrize(
    ("prior", "irregular"), [(True, False), (False, False), (True, True), (False, True)]
)
def test_fbs_equals_the_batch_least_squares(prior: bool, irregular: bool) -> None:
    """FBS with correlated sensors and lost measurements, with and without a prior, on regular
    and irregular instants, equals the batch weighted least squares over the whole run."""
    system = random_system(np.random.default_rng(80), 3, [1, 2], prior=prior, correlated=True)
    if irregular:
        system = on_irregular_instants(system, 8)
    mask = mask_of(system, 12, 0.2)
    if not prior:
        system = dataclasses.replace(system, initial=Prior(np.zeros(3), np.eye(3)))
    z = data_of(system, mask)
    mean, cov, cond = batch_smoother(system, z, mask)
    assert cond < 1e10
    assert_equals_reference(system, "FBS", z, mean, cov)


def gmf_of_information_vectors(system: System, z: np.ndarray, mask: np.ndarray):
    """MSC-GMF without a prior from its definition: the locals are information filters whose
    vectors are y_j = Y_j x + eps_j; the joint covariance of the eps_j (exactly, by
    superposition: eps is linear in the noises) and the constraint sum_j W_j Y_j = I give the
    best linear unbiased combination x = sum_j W_j y_j, P = W Sigma W^T (min tr P, solved on
    the null space of the constraint). NaN where the constraint cannot be met."""
    groups = [np.arange(system.m)[sl] for sl in system.sensor_slices]
    X, Zb = basis_runs(system, mask)
    basis = [information_filter(system, Zb, mask, [g]) for g in groups]
    data = [information_filter(system, z, mask, [g]) for g in groups]
    n, M = system.n, z.shape[0]
    mean, cov = np.full((M, K + 1, n), np.nan), np.full((K + 1, n, n), np.nan)
    for k in range(K + 1):
        E = np.vstack([b[0][k] for b in basis])  # (S n, n): the stacked Y_j
        if np.linalg.matrix_rank(E, tol=1e-9 * np.abs(E).max()) < n:
            continue
        eps = np.concatenate([b[1][:, k] - X[:, k] @ b[0][k] for b in basis], axis=1)
        A = eps[1:] - eps[0]
        Sigma = A.T @ A + np.outer(eps[0], eps[0])
        # W = W0 + Z N^T with W0 E = I and N spanning the null space of E^T
        W0 = np.linalg.pinv(E)
        U, sv, _ = np.linalg.svd(E)
        N = U[:, n:]
        G = N.T @ Sigma @ N
        # min-norm: a local without information (Y_j = 0, eps_j = 0) takes any weight
        Zw = -np.linalg.lstsq(G, (W0 @ Sigma @ N).T, rcond=1e-12)[0].T
        W = W0 + Zw @ N.T
        cov[k] = W @ Sigma @ W.T
        mean[:, k] = np.concatenate([d[1][:, k] for d in data], axis=1) @ W.T
    return mean, cov


def test_msc_gmf_without_prior_is_the_best_combination_of_the_information_vectors() -> None:
    """Without a prior the locals are information filters (a single sensor may see too little
    for a covariance): MSC-GMF equals the best linear unbiased combination of their
    information vectors, built here from the definition, with correlated sensors and lost
    measurements."""
    system = random_system(np.random.default_rng(90), 3, [1, 2], prior=False, correlated=True)
    mask = mask_of(system, 13, 0.2)
    z = data_of(system, mask)
    mean, cov = gmf_of_information_vectors(system, z, mask)
    compute = estimate_ours("MSC-GMF", z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    both = ~np.isnan(cov).any(axis=(1, 2)) & ~np.isnan(got.cov).any(axis=(1, 2))
    assert both.sum() >= K - 2
    assert_agree(got.mean[both], np.swapaxes(mean, 0, 1)[both], sens.tolerance("mean"),
                 sens.unsettled[both], "mean")  # fmt: skip
    assert_agree(got.cov[both], cov[both], sens.tolerance("cov"), sens.unsettled[both], "cov")
