"""Static fusion rules: Millman, Bar-Shalom-Campo, generalised Millman, covariance intersection."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_spd, random_system
from hypothesis import given, settings
from hypothesis import strategies as st

from fusionlog.core.architectures import build_plan
from fusionlog.core.fusion import (
    bar_shalom_campo,
    ci_omega,
    ci_omegas,
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
    """Every omega on the simplex with coordinates in multiples of 1/steps."""
    if N == 1:
        return np.ones((1, 1))
    rows = [
        np.column_stack([np.full(len(rest), k / steps), rest * (1.0 - k / steps)])
        for k in range(steps + 1)
        for rest in [_simplex_grid(N - 1, steps - k) if k < steps else np.zeros((1, N - 1))]
    ]
    return np.vstack(rows)


def _refine(best: np.ndarray, covs: list[np.ndarray], criterion: str, radius: float):
    """Random search around `best` with a shrinking radius (the cost is convex, so this closes
    in on the optimum): the brute force's answer below a grid's resolution."""
    rng = np.random.default_rng(0)
    N = len(best)
    cost = _ci_costs_on(best[None], covs, criterion)[0]
    for _ in range(40):
        u = rng.uniform(-1.0, 1.0, (1500, N))
        cand = np.maximum(best + radius * (u - u.mean(axis=1, keepdims=True)), 0.0)
        cand = np.vstack([cand / cand.sum(axis=1, keepdims=True), np.eye(N)])
        with np.errstate(invalid="ignore"):
            costs = _ci_costs_on(cand, covs, criterion)
        k = np.nanargmin(costs)
        if costs[k] < cost:
            best, cost = cand[k], costs[k]
        else:
            radius /= 2
    return best, cost


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("N", [2, 3, 4, 5])
def test_ci_omega_is_the_optimum_of_a_brute_force_search(N, criterion):
    """On random unequal covariances, ci_omega's weights cost no more (to 1e-13) than the best
    point of a grid on the simplex refined by a random search around it (the cost is convex,
    so that is the optimum up to the search's resolution). A uniform omega or an end point
    would fail: the cases are checked to tell them apart."""
    rng = np.random.default_rng(100 * N + len(criterion))
    steps = {2: 4000, 3: 300, 4: 40, 5: 16}[N]
    grid = _simplex_grid(N, steps)
    told_apart = 0
    for _ in range(8):
        n = int(rng.integers(2, 4))
        covs = [_elongated(rng, n) for _ in range(N)]
        om = ci_omega(covs, criterion)
        assert om.shape == (N,) and np.all(om >= 0) and abs(om.sum() - 1) < 1e-12
        with np.errstate(invalid="ignore"):
            costs = _ci_costs_on(grid, covs, criterion)
        best, cost = _refine(grid[np.nanargmin(costs)], covs, criterion, 1.0 / steps)
        got = _ci_costs_on(om[None], covs, criterion)[0]
        assert got <= cost + 1e-13 * max(abs(cost), 1.0), (om, best, got, cost)
        # The answers of the mutations: a uniform omega and each end point.
        others = _ci_costs_on(np.vstack([np.full(N, 1.0 / N), np.eye(N)]), covs, criterion)
        told_apart += bool(np.all(others > cost + 1e-6 * max(abs(cost), 1.0)))
    assert told_apart >= 2  # cases where a uniform omega and every end point would fail


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


def _ci_problems(rng: np.random.Generator, B: int, N: int, n: int) -> np.ndarray:
    """B CI problems (B, N, n, n) of every kind: inputs good in different directions (interior
    optima), one input better than the others by a positive semidefinite term (an end point
    wins), inputs equal up to 1e-6, two equal inputs, and inputs that do not see the whole
    state (singular informations) whose sum does."""
    out = np.empty((B, N, n, n))
    for b in range(B):
        kind = b % 5
        Y = np.stack([np.linalg.inv(_elongated(rng, n)) for _ in range(N)])
        if kind == 1:  # Y_i = L M_i L^T <= Y_k = L L^T: M_i's eigenvalues in (0.1, 1)
            L = np.linalg.cholesky(Y[0])
            for i in range(1, N):
                V, _ = np.linalg.qr(rng.standard_normal((n, n)))
                Y[i] = L @ V @ np.diag(rng.uniform(0.1, 1.0, n)) @ V.T @ L.T
            Y = Y[rng.permutation(N)]
        elif kind == 2:
            E = rng.standard_normal((N, n, n))
            Y = Y[0] + 1e-6 * (E + np.swapaxes(E, 1, 2))
        elif kind == 3:
            Y[1] = Y[0]
        elif kind == 4:
            for i in range(N - 1):  # rank n - 1: blind along a random direction
                v = rng.standard_normal(n)
                Y[i] = Y[i] - np.outer(Y[i] @ v, Y[i] @ v) / (v @ Y[i] @ v)
        out[b] = 0.5 * (Y + np.swapaxes(Y, 1, 2))
    return out


def _fw_gap(W: np.ndarray, Ys: np.ndarray, criterion: str) -> np.ndarray:
    """The Frank-Wolfe gap g^T w - min_i g_i of each problem at its answer, relative to the
    cost scale (tr P; 1 for log det P), with plain numpy: g_i = -tr(P Y_i P) or -tr(P Y_i).
    The cost is convex, so the answer's cost is within this gap of the optimum."""
    P = np.linalg.inv(np.einsum("bi,biac->bac", W, Ys))
    if criterion == "trace":
        g = -np.einsum("bac,bicd,bda->bi", P, Ys, P)
        scale = np.trace(P, axis1=1, axis2=2)
    else:
        g = -np.einsum("bac,bica->bi", P, Ys)
        scale = 1.0
    return ((W * g).sum(axis=1) - g.min(axis=1)) / scale


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize(
    ("n", "N"), [(1, 3), (2, 2), (2, 3), (2, 4), (2, 5), (3, 3), (3, 5), (4, 4)]
)
def test_ci_omegas_are_optimal_to_1e12(n, N, criterion):
    """For every kind of problem, the weights are optimal to 1e-12 of the cost, certified by
    the Frank-Wolfe gap (an upper bound on the cost above the optimum, for a convex cost)."""
    rng = np.random.default_rng(10 * n + N + len(criterion))
    Ys = _ci_problems(rng, 200, N, n)
    W = ci_omegas(Ys, criterion)
    assert np.all(W >= 0) and np.allclose(W.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    gap = _fw_gap(W, Ys, criterion)
    assert gap.max() < 1e-12, (gap.max(), W[gap.argmax()])


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize(("n", "N"), [(2, 3), (2, 4), (3, 3)])
def test_ci_omegas_do_not_depend_on_the_batch(n, N, criterion):
    """A problem's weights are the same to the last bit alone, in a batch with others in any
    order, and in an array of another shape and memory layout (the per-run path hands the
    solver (steps, runs) problems in the local filters' layout)."""
    rng = np.random.default_rng(3 * n + N)
    Ys = _ci_problems(rng, 60, N, n)
    Ys[7, :] = np.zeros((n, n))  # no information at all: NaN
    together = ci_omegas(Ys, criterion)
    alone = np.vstack([ci_omegas(Ys[b : b + 1], criterion) for b in range(len(Ys))])
    assert np.array_equal(together, alone, equal_nan=True)
    order = rng.permutation(len(Ys))
    assert np.array_equal(ci_omegas(Ys[order], criterion), together[order], equal_nan=True)
    # (runs, steps) problems stored runs-innermost, as a view with the steps first.
    base = np.ascontiguousarray(np.moveaxis(Ys.reshape(6, 10, N, n, n), 0, -1))
    view = np.moveaxis(base, -1, 0)
    assert not view.flags.c_contiguous
    got = ci_omegas(view, criterion)
    assert got.shape == (6, 10, N)
    assert np.array_equal(got.reshape(-1, N), together, equal_nan=True)
    assert np.isnan(together[7]).all() and np.isfinite(np.delete(together, 7, axis=0)).all()


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("n", [1, 2, 3])
def test_ci_equal_inputs_share_the_weight(n, criterion):
    """Equal covariances: omega = 1/N exactly (every omega gives the same P; the average of the
    estimates is the answer that does not jump with rounding), also when they differ by an
    ulp; two equal inputs beside others get equal weights."""
    rng = np.random.default_rng(n)
    for N in range(2, 6):
        Y = np.linalg.inv(_elongated(rng, n))
        Ys = np.stack([Y] * N)
        assert np.array_equal(ci_omegas(Ys[None], criterion)[0], np.full(N, 1.0 / N))
        Ys[1, 0, 0] = np.nextafter(Ys[1, 0, 0], np.inf)
        assert np.array_equal(ci_omegas(Ys[None], criterion)[0], np.full(N, 1.0 / N))
        Ys = np.stack([np.linalg.inv(_elongated(rng, n)) for _ in range(N)])
        Ys[-1] = Ys[0]
        w = ci_omegas(Ys[None], criterion)[0]
        assert w[0] == w[-1]
        assert _fw_gap(w[None], Ys[None], criterion)[0] < 1e-12


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("n", [2, 3])
def test_ci_singular_inputs(n, criterion):
    """Inputs that do not see the whole state (singular informations, infinite cost on part of
    the simplex) still fuse to the optimum when their sum is invertible; a problem whose
    inputs together are singular has no CI estimate (NaN)."""
    E = np.eye(n)
    # Each input sees one coordinate: the cost is sum_k 1/w_k (trace) or -sum_k log w_k (det),
    # whose optimum is w = 1/n each.
    Ys = np.stack([np.outer(E[k], E[k]) * (k + 1.0) for k in range(n)])[None]
    w = ci_omegas(Ys, criterion)[0]
    if criterion == "det":
        np.testing.assert_allclose(w, np.full(n, 1.0 / n), rtol=0, atol=1e-14)
    assert _fw_gap(w[None], Ys, criterion)[0] < 1e-12
    # One input blind along a direction beside a regular one: both may keep weight.
    rng = np.random.default_rng(n)
    Yr = np.linalg.inv(_elongated(rng, n))
    blind = np.outer(E[0], E[0]) * 5.0
    Ys = np.stack([blind, Yr])[None]
    w = ci_omegas(Ys, criterion)[0]
    assert np.isfinite(w).all() and w[1] > 0
    assert _fw_gap(w[None], Ys, criterion)[0] < 1e-12
    # Nothing sees the last coordinate: no estimate.
    Ys = np.stack([blind, 2.0 * blind, np.outer(E[0] + E[1], E[0] + E[1]) * (n > 2)])[None]
    if n == 2:
        Ys = Ys[:, :2]
    assert np.isnan(ci_omegas(Ys, criterion)).all()


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_shared_and_per_run_paths_agree(criterion):
    """Different sensors (interior optima): the shared path's omegas and those of a per-run
    build with nothing missing agree to 1e-12 (the same solver on the same problems; the
    local filters' covariances differ between the paths by rounding only)."""
    rng = np.random.default_rng(4)
    for system in (random_system(rng, 2, [1, 2, 1]), random_system(rng, 3, [1, 2, 1, 2])):
        K = 12
        shared = build_plan(system, "CI", K, None, criterion).omega
        per_run = build_plan(system, "CI", K, np.ones((5, K + 1, system.m), bool), criterion).omega
        assert per_run.shape == (5,) + shared.shape
        assert ((shared > 0) & (shared < 1)).any()
        np.testing.assert_allclose(
            per_run, np.broadcast_to(shared, per_run.shape), rtol=0, atol=1e-12
        )


@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("N", [2, 3, 4])
def test_ci_routes_agree(N, criterion):
    """n = 2 problems are settled by exact tests at 1/N and at the end points, closed forms on
    the edges, or the active-set Newton method; each route's answer is certified optimal, and
    the Newton method alone (with the n = 2 rational costs, and with the matrix costs of any
    n) finds the same costs on every problem."""
    from fusionlog.core.ci_newton import Info2, InfoN, finish, representatives

    rng = np.random.default_rng(N + len(criterion))
    Ys = _ci_problems(rng, 100, N, 2)
    Ys = Ys / np.trace(Ys.mean(axis=1), axis1=1, axis2=2)[:, None, None, None]  # unit scale
    trace = criterion == "trace"
    rep = representatives(lambda k, i: (Ys[:, k] == Ys[:, i]).all(axis=(1, 2)), len(Ys), N)
    with np.errstate(all="ignore"):  # as in ci_omegas: infeasible trial points cost inf
        answers = [
            ci_omegas(Ys, criterion),
            finish(Info2.of(Ys[..., 0, 0], Ys[..., 0, 1], Ys[..., 1, 1], trace), rep),
            finish(InfoN.of(Ys, trace), rep),
        ]
    costs = []
    for W in answers:
        assert _fw_gap(W, Ys, criterion).max() < 1e-12
        P = np.linalg.inv(np.einsum("bi,biac->bac", W, Ys))
        costs.append(np.trace(P, axis1=1, axis2=2) if trace else np.linalg.slogdet(P)[1])
    scale = np.abs(costs[0]) if trace else 1.0
    for c in costs[1:]:
        assert np.max(np.abs(c - costs[0]) / scale) < 1e-13
