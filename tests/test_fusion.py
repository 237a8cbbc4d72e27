"""Static fusion rules: Millman, Bar-Shalom-Campo, generalised Millman, covariance intersection."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_spd
from hypothesis import given, settings
from hypothesis import strategies as st

from fusionlog.core.fusion import (
    bar_shalom_campo,
    ci_omega,
    ci_weights,
    fuse,
    gmf_weights,
    millman_weights,
)


def _joint(rng, n, N, corr=0.5):
    """A random SPD joint covariance of N estimates with correlated blocks."""
    A = rng.standard_normal((N * n, N * n))
    common = rng.standard_normal((n, N * n))
    return (
        A @ A.T / (N * n)
        + corr
        * np.tile(np.eye(n), (N, 1))
        @ common
        @ common.T
        @ np.tile(np.eye(n), (1, N))
        / (N * n)
        + 0.1 * np.eye(N * n)
    )


def _block(J, n, i, j):
    return J[i * n : (i + 1) * n, j * n : (j + 1) * n]


def test_millman_two_estimates_closed_form():
    rng = np.random.default_rng(0)
    P1, P2 = random_spd(rng, 3), random_spd(rng, 3)
    (c1, c2), P = millman_weights([P1, P2])
    S = np.linalg.inv(P1 + P2)
    np.testing.assert_allclose(c1, P2 @ S, atol=1e-12)  # eq. (10)
    np.testing.assert_allclose(c2, P1 @ S, atol=1e-12)
    np.testing.assert_allclose(P, P1 @ S @ P2, atol=1e-12)  # eq. (11)
    np.testing.assert_allclose(c1 + c2, np.eye(3), atol=1e-12)  # eq. (3)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 4))
def test_gmf_two_estimates_equals_bar_shalom_campo(seed, n):
    rng = np.random.default_rng(seed)
    J = _joint(rng, n, 2)
    (g1, g2), Pg = gmf_weights(J, n)
    (b1, b2), Pb = bar_shalom_campo(_block(J, n, 0, 0), _block(J, n, 1, 1), _block(J, n, 0, 1))
    np.testing.assert_allclose(g1, b1, atol=1e-9)
    np.testing.assert_allclose(g2, b2, atol=1e-9)
    np.testing.assert_allclose(Pg, Pb, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 4), N=st.integers(2, 5))
def test_gmf_without_cross_covariance_equals_millman(seed, n, N):
    rng = np.random.default_rng(seed)
    covs = [random_spd(rng, n) for _ in range(N)]
    J = np.zeros((N * n, N * n))
    for i, P in enumerate(covs):
        J[i * n : (i + 1) * n, i * n : (i + 1) * n] = P
    wg, Pg = gmf_weights(J, n)
    wm, Pm = millman_weights(covs)
    for a, b in zip(wg, wm, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(Pg, Pm, atol=1e-9)


def test_gmf_is_optimal_on_correlated_estimates():
    """No other weights summing to I give a smaller fused covariance (eq. 5)."""
    rng = np.random.default_rng(3)
    n, N = 2, 3
    J = _joint(rng, n, N)
    w, P = gmf_weights(J, n)
    np.testing.assert_allclose(sum(w), np.eye(n), atol=1e-10)
    for _ in range(50):
        D = [0.1 * rng.standard_normal((n, n)) for _ in range(N - 1)]
        alt = [w[i] + D[i] for i in range(N - 1)] + [w[-1] - sum(D)]
        C = np.hstack(alt)
        assert np.all(np.linalg.eigvalsh(C @ J @ C.T - P) > -1e-10)


def test_gmf_singular_joint_covariance_paper_structure():
    """Local KFs with a common prior and identical position-only sensors: the stacked covariance
    11^T (x) A + I (x) B with rank-one B is singular; the constrained LS form still works, the
    weights are the plain average by symmetry, and P is the limit of the regularised problem."""
    rng = np.random.default_rng(5)
    n, N = 2, 3
    A = random_spd(rng, n)
    b = rng.standard_normal(n)
    J = np.kron(np.ones((N, N)), A) + np.kron(np.eye(N), np.outer(b, b))
    assert np.linalg.matrix_rank(J) < N * n
    w, P = gmf_weights(J, n)
    np.testing.assert_allclose(sum(w), np.eye(n), atol=1e-10)
    _, P_reg = gmf_weights(J + 1e-9 * np.eye(N * n), n)
    np.testing.assert_allclose(P, P_reg, atol=1e-7)
    np.testing.assert_allclose(P, A + np.outer(b, b) / N, atol=1e-10)
    # Estimates differing only by a null direction of J fuse to the same value.
    xs = [rng.standard_normal(n) for _ in range(N)]
    x_avg = sum(xs) / N
    np.testing.assert_allclose(
        fuse(w, xs) - x_avg, fuse([np.eye(n) / N] * N, xs) - x_avg, atol=1e-8
    )


def test_ci_end_points_return_an_input():
    rng = np.random.default_rng(1)
    P1, P2 = random_spd(rng, 2), random_spd(rng, 2)
    for om, P_expect, c_expect in (([1.0, 0.0], P1, 0), ([0.0, 1.0], P2, 1)):
        ws, P = ci_weights([P1, P2], np.array(om))
        np.testing.assert_allclose(P, P_expect, atol=1e-12)
        np.testing.assert_allclose(ws[c_expect], np.eye(2), atol=1e-12)
        np.testing.assert_allclose(ws[1 - c_expect], np.zeros((2, 2)), atol=1e-12)
    # One input strictly better than the other: the optimiser keeps it alone.
    assert np.array_equal(ci_omega([0.5 * P2, P2]), [1.0, 0.0])
    assert np.array_equal(ci_omega([P1, 3.0 * P1], "det"), [1.0, 0.0])


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 3),
    rho=st.floats(-0.99, 0.99),
    criterion=st.sampled_from(["trace", "det"]),
)
def test_ci_bounds_true_error_covariance(seed, n, rho, criterion):
    """Whatever the (unknown) cross-covariance, the CI covariance bounds the true one."""
    rng = np.random.default_rng(seed)
    P1, P2 = random_spd(rng, n), random_spd(rng, n)
    L1, L2 = np.linalg.cholesky(P1), np.linalg.cholesky(P2)
    Qo, _ = np.linalg.qr(rng.standard_normal((n, n)))
    P12 = rho * L1 @ Qo @ L2.T  # any such P12 keeps the joint covariance PSD
    om = ci_omega([P1, P2], criterion)
    (c1, c2), P = ci_weights([P1, P2], om)
    true = c1 @ P1 @ c1.T + c1 @ P12 @ c2.T + c2 @ P12.T @ c1.T + c2 @ P2 @ c2.T
    assert np.linalg.eigvalsh(P - true).min() > -1e-9 * np.abs(P).max()
    assert abs(om.sum() - 1) < 1e-12 and np.all(om >= 0)


def test_ci_three_estimates():
    rng = np.random.default_rng(2)
    covs = [random_spd(rng, 2) for _ in range(3)]
    om = ci_omega(covs, "trace")
    _, P = ci_weights(covs, om)
    for i in range(3):  # never worse than the best single input
        assert np.trace(P) <= np.trace(covs[i]) + 1e-9


def _ci_costs_on(omegas: np.ndarray, covs: list[np.ndarray], criterion: str) -> np.ndarray:
    """tr(P) or log det(P) of P = (sum_i w_i P_i^-1)^-1 for each row w of `omegas`, written out
    here with plain numpy (no fusionlog code)."""
    infos = np.stack([np.linalg.inv(P) for P in covs])
    Y = np.einsum("gi,iab->gab", omegas, infos)
    if criterion == "trace":
        return np.trace(np.linalg.inv(Y), axis1=-2, axis2=-1)
    return -np.linalg.slogdet(Y)[1]


def _elongated(rng: np.random.Generator, n: int) -> np.ndarray:
    """A covariance with eigenvalues spread over e^-2..e^2 along random directions: inputs that
    are each good in some direction, so that CI's optimum is usually interior."""
    V, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return V @ np.diag(np.exp(rng.uniform(-2.0, 2.0, n))) @ V.T


def _simplex_grid(N: int, steps: int) -> np.ndarray:
    """Every omega on the simplex with coordinates in multiples of 1/steps (N = 2 or 3)."""
    if N == 2:
        w = np.linspace(0.0, 1.0, steps + 1)
        return np.stack([w, 1.0 - w], axis=1)
    i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1), indexing="ij")
    keep = i + j <= steps
    a, b = i[keep] / steps, j[keep] / steps
    return np.stack([a, b, 1.0 - a - b], axis=1)


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("N", [2, 3])
def test_ci_omega_is_the_optimum_of_a_brute_force_search(N, criterion):
    """On random unequal covariances, ci_omega's weights cost no more than the best point of a
    fine grid on the simplex (the cost is convex, so that is the optimum up to the grid). A
    uniform omega or an end point would fail: the cases are checked to tell them apart."""
    rng = np.random.default_rng(100 * N + len(criterion))
    steps = 4000 if N == 2 else 300
    grid = _simplex_grid(N, steps)
    told_apart = 0
    for _ in range(12):
        n = int(rng.integers(2, 4))
        covs = [_elongated(rng, n) for _ in range(N)]
        om = ci_omega(covs, criterion)
        assert om.shape == (N,) and np.all(om >= 0) and abs(om.sum() - 1) < 1e-12
        costs = _ci_costs_on(grid, covs, criterion)
        best = costs.min()
        got = _ci_costs_on(om[None], covs, criterion)[0]
        assert got <= best + 1e-10 * abs(best), (om, grid[costs.argmin()], got, best)
        # The answers of the mutations: a uniform omega and each end point.
        others = _ci_costs_on(np.vstack([np.full(N, 1.0 / N), np.eye(N)]), covs, criterion)
        told_apart += bool(np.all(others > best + 1e-6 * abs(best)))
    assert told_apart >= 3  # cases where a uniform omega and every end point would fail


def test_ci_omega_matches_the_grid_optimum_of_two_inputs():
    """Two inputs: the optimal omega itself (not only its cost) is the grid's, to its step."""
    rng = np.random.default_rng(7)
    grid = _simplex_grid(2, 20000)
    for _ in range(10):
        covs = [_elongated(rng, 2) for _ in range(2)]
        om = ci_omega(covs, "trace")
        costs = _ci_costs_on(grid, covs, "trace")
        k = costs.argmin()
        if 0 < k < len(grid) - 1:  # interior: a flat minimum is located to about its curvature
            assert abs(om[0] - grid[k, 0]) < 2e-3, (om, grid[k])
