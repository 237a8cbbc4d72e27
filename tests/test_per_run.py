"""The per-run path (runs with their own measurement patterns, e.g. random dropouts) against
the shared path and against FilterPy.

The per-run path computes with the batch kernels of `core.linalg` (products, Cholesky and LU
solves, inverses written entry by entry over the runs) once the batch is large, groups the
runs by measurement history (`HistoryNodes`) and runs the plan on the runs-last layout. Each
test runs three ways: `nodes` (what `estimate` does: maps per history, the kernels wherever a
step has at least `kernels.KERNEL_MIN_BATCH` histories), `runs` (no grouping: 80 runs through
the kernels at every step) and `forced` (grouping, and the kernels for every batch, even one
matrix).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conditioning import assert_agree, sensitivity
from conftest import random_spd, random_system
from filterpy.kalman import KalmanFilter

from fusionlog.core import kernels, linalg
from fusionlog.core.architectures import (
    STATE_ARCHITECTURES,
    HistoryNodes,
    build_plan,
    estimate,
    registry,
    run_plan,
)
from fusionlog.core.model import Prior, System, ajgl2009
from fusionlog.core.simulate import simulate
from fusionlog.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
#: Agreement of the per-run and the shared path, relative to the size of the numbers.
RTOL = 1e-12
M, K = 80, 12


@pytest.fixture(params=["nodes", "runs", "forced"])
def path(request, monkeypatch) -> str:
    if request.param == "runs":
        monkeypatch.setattr(registry, "NODES_AT_MOST", 0.0)
    if request.param == "forced":
        monkeypatch.setattr(kernels, "KERNEL_MIN_BATCH", 1)
    return request.param


def assert_close(actual: np.ndarray, desired: np.ndarray, rtol: float, what: str) -> None:
    """The same undefined (NaN) entries, the others to rtol relative to the largest one."""
    np.testing.assert_array_equal(np.isnan(actual), np.isnan(desired), err_msg=what)
    ok = ~np.isnan(desired)
    scale = np.abs(desired[ok]).max(initial=0.0)
    np.testing.assert_allclose(actual[ok], desired[ok], rtol=rtol, atol=rtol * scale, err_msg=what)


def _system(seed: int, prior: bool, correlated: bool) -> System:
    """Heterogeneous sensors. Without a prior every sensor sees the whole state, so that each
    filter's information is well conditioned from k = 0: where a filter becomes invertible only
    after a few steps, its first covariance is the inverse of an information of condition
    number ~1e5 and any two ways of computing it (LU and Cholesky, or BLAS and einsum sums)
    agree only to ~1e-16 times that."""
    rng = np.random.default_rng(seed)
    if prior:
        return random_system(rng, 3, [1, 2, 1], prior=True, correlated=correlated)
    return random_system(rng, 2, [2, 3, 2], prior=False, correlated=correlated)


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
@pytest.mark.parametrize("prior", [True, False], ids=["prior", "no-prior"])
@pytest.mark.parametrize("correlated", [False, True], ids=["indep", "correlated"])
def test_per_run_path_equals_shared_path(path, arch, prior, correlated):
    """A pattern shared by all runs, passed per run ((M, K+1, m) mask), gives the shared plan's
    means and covariances to 1e-12: every measurement present, and a pattern with gaps."""
    system = _system(11 + correlated, prior, correlated)
    _, z = simulate(system, K, 3, 0, M)
    gaps = np.random.default_rng(5).random((K + 1, system.m)) > 0.25
    for pattern in (np.ones((K + 1, system.m), bool), gaps):
        zz = np.where(pattern, z, np.nan)
        shared = run_plan(build_plan(system, arch, K, None if pattern.all() else pattern), zz)
        per_run_plan = build_plan(
            system, arch, K, np.broadcast_to(pattern, z.shape), history_nodes=True
        )
        assert per_run_plan.per_run
        per_run = run_plan(per_run_plan, zz)
        assert per_run.cov.ndim == 4 and shared.cov.ndim == 3
        what = f"{arch}, {'complete' if pattern.all() else 'gaps'}"
        assert_close(per_run.mean, shared.mean, RTOL, f"{what}: mean")
        assert_close(per_run.cov, np.broadcast_to(shared.cov, per_run.cov.shape), RTOL, what)


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_every_run_equals_the_shared_plan_of_its_own_pattern(path, arch):
    """Random dropouts (every run its own pattern): each run's estimate is the shared plan's
    for that run's mask, whichever runs share its history."""
    system = _system(21, True, True)
    _, z = simulate(system, K, 4, 0, M)
    z[np.random.default_rng(6).random(z.shape) < 0.2] = np.nan
    est = estimate(system, z, arch)
    assert est.cov.ndim == 4
    for r in range(0, M, 9):

        def own_estimate(s, r=r):
            e = run_plan(build_plan(s, arch, K, ~np.isnan(z[r])), z[r : r + 1])
            return SimpleNamespace(mean=e.mean[0], cov=e.cov)

        own = own_estimate(system)
        # The two paths solve the same problems in other orders: they agree to what rounding
        # can move the answer by (the generalised Millman system here is near singular).
        sens = sensitivity(own_estimate, system, ("mean", "cov"))
        for f in ("mean", "cov"):
            tol = sens.tolerance(f, RTOL)
            assert_agree(
                getattr(est, f)[r], getattr(own, f), tol, sens.unsettled, f"{arch} {r} {f}"
            )


def test_build_plan_gathers_the_nodes_into_per_run_maps(path):
    """`build_plan` hands out maps with a run axis (what the exact analysis cuts by run); with
    `history_nodes` the maps stay per history, and both run to the same estimates."""
    system = ajgl2009()
    _, z = simulate(system, K, 2, 0, M)
    z[np.random.default_rng(1).random(z.shape) < 0.1] = np.nan
    present = ~np.isnan(z)
    for arch in ("CKF", "MSC-GMF", "FBS"):
        runs = build_plan(system, arch, K, present)
        nodes = build_plan(system, arch, K, present, history_nodes=True)
        assert runs.nodes is None
        assert all(np.shape(st.P)[0] == M for st in runs.steps)
        a, b = run_plan(runs, z), run_plan(nodes, z)
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)


def test_history_nodes_group_runs_with_equal_histories():
    rng = np.random.default_rng(2)
    for m in (3, 6, 20):  # small masks numbered directly, larger ones by packed bits
        present = rng.random((300, 9, m)) > (0.1 if m < 20 else 0.02)
        nodes = HistoryNodes.of(present)
        for k in range(9):
            idx = nodes.index[k]
            prefix = present[:, : k + 1].reshape(300, -1)
            distinct = np.unique(prefix, axis=0)
            assert len(nodes.parent[k]) == len(distinct) == idx.max() + 1
            for u in range(len(distinct)):
                runs = np.flatnonzero(idx == u)
                assert (prefix[runs] == prefix[runs[0]]).all()
                np.testing.assert_array_equal(nodes.present[k][u], present[runs[0], k])
            np.testing.assert_array_equal(nodes.parent[k][idx], nodes.index[k - 1] if k else 0)
        assert nodes.count == sum(len(np.unique(present[:, : k + 1].reshape(300, -1), axis=0))
                                  for k in range(9))  # fmt: skip


# --------------------------------------------------------------------------------------------
# FilterPy, one run at a time, on the present components only


def filterpy_run(system: System, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """FilterPy's KalmanFilter on one run z (K+1, m): at each step the update uses the rows of
    H and the block of R (cross-covariances included) of the components present; a step with
    none is a pure prediction. Update at k = 0, predict then update after."""
    n, H, R = system.n, system.H, system.R
    kf = KalmanFilter(dim_x=n, dim_z=system.m)
    kf.F, kf.Q = system.F.copy(), system.GQG.copy()
    kf.x, kf.P = system.prior.mean.astype(float).copy(), system.prior.cov.astype(float).copy()
    xs, Ps = [], []
    for k in range(z.shape[0]):
        if k > 0:
            kf.predict()
        ok = ~np.isnan(z[k])
        if ok.any():
            kf.dim_z = int(ok.sum())  # FilterPy checks z against dim_z
            kf.update(z[k, ok], R=R[np.ix_(ok, ok)], H=H[ok])
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("correlated", [False, True], ids=["indep", "correlated"])
def test_per_run_ckf_equals_filterpy_without_the_missing_rows(path, seed, correlated):
    """Per-run CKF (random dropouts, 80 runs) against FilterPy run by run with the missing
    sensors' rows removed, to 1e-9 relative to the size of the numbers."""
    rng = np.random.default_rng(30 + seed)
    system = random_system(rng, 3, [1, 2, 2, 1], correlated=correlated)
    _, z = simulate(system, 20, seed, 0, M)
    z[rng.random(z.shape) < 0.2] = np.nan
    z[0, 3] = np.nan  # nothing at all at one step
    est = estimate(system, z, "CKF")
    assert est.cov.ndim == 4
    ref = [filterpy_run(system, z[r]) for r in range(M)]
    mean, cov = np.stack([x for x, _ in ref]), np.stack([P for _, P in ref])
    assert_close(est.mean, mean, 1e-9, "mean")
    assert_close(est.cov, cov, 1e-9, "cov")


# --------------------------------------------------------------------------------------------
# The kernels themselves


def test_kernels_equal_numpy_and_redo_what_they_cannot_factor(monkeypatch):
    """mm, solve (Cholesky and pivoted LU), spd_inv, inv_or_nan and is_invertible on a large
    batch equal numpy's routines to rounding; singular matrices take numpy's route one by one
    (the pseudo-inverse solution, NaN inverses), and the results are in the lanes layout."""
    monkeypatch.setattr(kernels, "KERNEL_MIN_BATCH", 64)
    rng = np.random.default_rng(0)
    B = 200
    for n in (1, 2, 3, 5):
        A = rng.standard_normal((B, n, n))
        S = np.stack([random_spd(rng, n) for _ in range(B)])
        X = rng.standard_normal((B, n, 2))
        S[7] = np.ones((n, n))  # singular (rank 1)
        A[9, :, 0] = 0.0  # singular
        A[11] = np.eye(n)[::-1] * 1e-3 + np.triu(np.ones((n, n)), 1)  # needs pivoting
        out = linalg.mm(A, X)
        np.testing.assert_allclose(out, A @ X, rtol=1e-13, atol=1e-13)
        assert out.strides[0] == 8  # the runs are the contiguous axis
        np.testing.assert_allclose(linalg.mm(A[0], X), A[0] @ X, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(linalg.mm(A, X[0]), A @ X[0], rtol=1e-13, atol=1e-13)
        regular = np.ones(B, bool)
        regular[[7, 9]] = False
        for hermitian, M_ in ((True, S), (False, A)):
            got = linalg.solve(M_, X, hermitian=hermitian)
            want = np.linalg.solve(M_[regular], X[regular])
            np.testing.assert_allclose(got[regular], want, rtol=1e-9, atol=1e-9)
        if n > 1:
            np.testing.assert_allclose(
                linalg.solve(S, X, hermitian=True)[7], np.linalg.pinv(S[7]) @ X[7], atol=1e-12
            )
        inv = linalg.spd_inv(np.delete(S, 7, axis=0))
        np.testing.assert_allclose(inv, np.linalg.inv(np.delete(S, 7, axis=0)), rtol=1e-11)
        np.testing.assert_array_equal(inv, np.swapaxes(inv, -1, -2))
        ok = linalg.is_invertible(S)
        assert ok[7] == (n == 1) and ok[np.arange(B) != 7].all()
        nan_or_inv = linalg.inv_or_nan(S)
        assert np.isnan(nan_or_inv[7]).all() == (n > 1)
        S[8] = np.nan
        assert not linalg.is_invertible(S)[8] and np.isnan(linalg.inv_or_nan(S)[8]).all()


def test_kernels_keep_badly_scaled_matrices_accurate():
    """Cholesky does not need the Jacobi scaling `spd_inv_scaled` gives LU: a covariance of a
    position measured with R = 1e-300 inverts to full accuracy in every run."""
    A = np.broadcast_to(np.array([[1e-300, 1e-300], [1e-300, 0.05]]), (100, 2, 2))
    want = np.array([[1e300 + 20.0, -20.0], [-20.0, 20.0]])
    np.testing.assert_allclose(linalg.spd_inv_scaled(A), np.broadcast_to(want, A.shape), rtol=1e-13)


def test_no_prior_run_without_measurements_stays_undefined(path):
    """Without a prior, a run that has seen nothing has no estimate (NaN) in every
    architecture, while the others have theirs; the kernels leave it to LAPACK's routines."""
    base = ajgl2009()
    system = System(F=base.F, Q=base.Q, sensors=base.sensors, prior=None, initial=base.prior)
    _, z = simulate(system, K, 7, 0, M)
    z[0, :4] = np.nan
    for arch in STATE_ARCHITECTURES:
        if arch == "CI":
            continue  # its weights are another module's (ci.ci_omegas)
        est = estimate(system, z, arch)
        assert np.isnan(est.cov[0, :5]).all() or arch == "FBS", arch
        assert np.isfinite(est.mean[1:, 2:]).all(), arch


def test_prior_is_kept_per_history_node():
    """A far-away prior (UTM-sized) and dropouts: nodes and runs give the same numbers."""
    base = ajgl2009()
    system = System(
        F=base.F, Q=base.Q, sensors=base.sensors, prior=Prior(np.array([5e6, -1.0]), np.eye(2))
    )
    _, z = simulate(system, K, 8, 0, M)
    z[np.random.default_rng(3).random(z.shape) < 0.1] = np.nan
    for arch in ("CKF", "HKF", "MSC", "AVG"):
        nodes = estimate(system, z, arch)
        runs = run_plan(build_plan(system, arch, K, ~np.isnan(z)), z)
        np.testing.assert_allclose(nodes.mean, runs.mean, rtol=1e-15, atol=0)


@pytest.mark.parametrize("arch", STATE_ARCHITECTURES)
def test_irregular_instants_with_dropouts(path, arch):
    """A time-varying system (the multirate scenario's irregular instants: F and Q per
    interval) with random losses on top of its sensor schedule: each run is still the shared
    plan of its own pattern.

    MSC-GMF to 1e-4 only: at k = 2, 3 two of its local filters have nearly the same error and
    J of eq. (35) has eigenvalues 3e-10 beside 25; the weights then move by ~1e-16 times that
    condition number when J does by one rounding, and the per-run and the shared J differ by
    one (blockwise against BLAS sums): least squares on the two differs as much, 1e-5."""
    tol = 1e-4 if arch == "MSC-GMF" else RTOL
    sc = load_scenario(ROOT / "pipeline" / "multirate.toml")
    K = 30
    system = sc.system.on_times(sc.schedule.times[: K + 1])
    assert not system.time_invariant
    sched = np.repeat(sc.schedule.measures[: K + 1], [s.dim for s in system.sensors], axis=1)
    _, z = simulate(system, K, 9, 0, M)
    z[~(sched & (np.random.default_rng(4).random(z.shape) > 0.2))] = np.nan
    est = estimate(system, z, arch)
    for r in range(0, M, 13):
        own = run_plan(build_plan(system, arch, K, ~np.isnan(z[r])), z[r : r + 1])
        assert_close(est.mean[r], own.mean[0], tol, f"{arch} run {r}: mean")
        assert_close(est.cov[r], own.cov, tol, f"{arch} run {r}: cov")
