"""FilterPy 1.4.5 as an independent reference for the Kalman-filter architectures.

On seeded random linear Gaussian models (n = 1..4 states, 1-5 sensors with random H and SPD R,
random stable-ish F, SPD Q, optional noise gain G, random prior) the centralised filter (CKF), the
single-sensor filters (SKF / SKF:<sensor>) and the fixed-interval smoother (FBS) must match a
plain FilterPy `KalmanFilter` loop to 1e-9 relative to the size of the numbers, means and
covariances alike, including runs with missing measurements (NaN).

Convention: the prior is p(x0 | z_{-1}), so at k = 0 the filter updates the prior with z_0 without
predicting; from k = 1 on it predicts, then updates. FilterPy's `batch_filter` predicts before
every update, so the reference runs FilterPy's predict/update by hand in that order and hands the
stored filtered estimates to `KalmanFilter.rts_smoother` for the smoother.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fusionlog.core.architectures import estimate
from fusionlog.core.model import Prior, Sensor, System, ajgl2009
from fusionlog.core.simulate import simulate

RTOL = 1e-9
RUNS = 3


# --------------------------------------------------------------------------------------------
# Random models


def _spd(rng: np.random.Generator, d: int, floor: float = 0.2) -> np.ndarray:
    """A random SPD matrix with eigenvalues bounded away from zero (condition number ~ 10-100)."""
    A = rng.standard_normal((d, d))
    return A @ A.T / d + floor * np.eye(d)


def _stable_ish(rng: np.random.Generator, n: int) -> np.ndarray:
    """A random F with spectral radius in [0.6, 1.05] (mildly unstable at most)."""
    F = rng.standard_normal((n, n))
    rho = np.max(np.abs(np.linalg.eigvals(F)))
    return F * rng.uniform(0.6, 1.05) / rho


def random_system(
    seed: int,
    n: int,
    n_sensors: int,
    *,
    correlated: bool = False,
    with_G: bool = False,
) -> System:
    """A random model. `correlated` draws one full SPD R for all sensors, so the sensors' noises
    are mutually dependent (off-diagonal blocks become `cross_R`); `with_G` uses a random noise
    gain G (n x q, q <= n), so the process noise G Q G^T may be singular."""
    rng = np.random.default_rng(seed)
    F = _stable_ish(rng, n)
    if with_G:
        q = int(rng.integers(1, n + 1))
        G = rng.standard_normal((n, q))
        Q = _spd(rng, q)
    else:
        G = None
        Q = _spd(rng, n)
    dims = [int(d) for d in rng.integers(1, 4, size=n_sensors)]
    Hs = [rng.standard_normal((d, n)) for d in dims]
    m = sum(dims)
    if correlated:
        Rfull = _spd(rng, m, floor=0.3)
    else:
        Rfull = np.zeros((m, m))
        start = 0
        for d in dims:
            Rfull[start : start + d, start : start + d] = _spd(rng, d, floor=0.3)
            start += d
    edges = np.cumsum([0, *dims])
    sensors = tuple(
        Sensor(f"s{j + 1}", Hs[j], Rfull[edges[j] : edges[j + 1], edges[j] : edges[j + 1]].copy())
        for j in range(n_sensors)
    )
    cross = {}
    if correlated:
        for i in range(n_sensors):
            for j in range(i + 1, n_sensors):
                cross[(i, j)] = Rfull[edges[i] : edges[i + 1], edges[j] : edges[j + 1]].copy()
    prior = Prior(rng.standard_normal(n) * 3.0, _spd(rng, n, floor=0.5))
    sys = System(F=F, Q=Q, G=G, sensors=sensors, prior=prior, cross_R=cross)
    np.testing.assert_array_equal(sys.R, Rfull)
    return sys


def _data(sys: System, steps: int, seed: int) -> np.ndarray:
    return simulate(sys, steps, seed, 0, RUNS)[1]


# --------------------------------------------------------------------------------------------
# The FilterPy reference


def filterpy_run(
    sys: System, z: np.ndarray, rows: np.ndarray, smooth: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """FilterPy on one run z (K+1, m) using the measurement components `rows` of the stacked
    vector (with the matching blocks of H and of the full R, cross-covariances included).

    NaN components are left out of that step's update (reduced H and R); a step with nothing
    present is a pure prediction. Returns filtered (or RTS-smoothed) means (K+1, n) and
    covariances (K+1, n, n).
    """
    n = sys.n
    H, R = sys.H[rows], sys.R[np.ix_(rows, rows)]
    kf = KalmanFilter(dim_x=n, dim_z=len(rows))
    kf.F = sys.F.copy()
    kf.Q = sys.GQG.copy()
    kf.H, kf.R = H.copy(), R.copy()
    kf.x = sys.prior.mean.astype(float).copy()
    kf.P = sys.prior.cov.astype(float).copy()
    xs, Ps = [], []
    for k in range(z.shape[0]):
        if k > 0:
            kf.predict()
        zk = z[k, rows]
        ok = ~np.isnan(zk)
        if ok.all():
            kf.update(zk)
        elif ok.any():
            kf.dim_z = int(ok.sum())  # FilterPy checks z against dim_z
            kf.update(zk[ok], R=R[np.ix_(ok, ok)], H=H[ok])
            kf.dim_z = len(rows)
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    Xs, Pst = np.array(xs), np.array(Ps)
    if smooth:
        N = len(Xs)
        Xs, Pst, _, _ = kf.rts_smoother(Xs, Pst, Fs=[sys.F] * N, Qs=[sys.GQG] * N)
    return Xs, Pst


def filterpy_all(
    sys: System, z: np.ndarray, rows: np.ndarray, smooth: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """`filterpy_run` for every run: means (M, K+1, n), covariances (M, K+1, n, n)."""
    outs = [filterpy_run(sys, z[r], rows, smooth) for r in range(z.shape[0])]
    return np.stack([o[0] for o in outs]), np.stack([o[1] for o in outs])


def assert_matches(est, ref_mean: np.ndarray, ref_cov: np.ndarray, what: str) -> None:
    """Means and covariances agree to RTOL relative to their scale (max |value|)."""
    cov = est.cov if est.cov.ndim == 4 else np.broadcast_to(est.cov, ref_cov.shape)
    assert est.mean.shape == ref_mean.shape, what
    assert cov.shape == ref_cov.shape, what
    assert np.isfinite(est.mean).all() and np.isfinite(cov).all(), what
    np.testing.assert_allclose(
        est.mean,
        ref_mean,
        rtol=RTOL,
        atol=RTOL * np.max(np.abs(ref_mean)),
        err_msg=f"{what}: mean",
    )
    np.testing.assert_allclose(
        cov, ref_cov, rtol=RTOL, atol=RTOL * np.max(np.abs(ref_cov)), err_msg=f"{what}: cov"
    )


# Seeded cases: (seed, n, sensors, with_G, K). Every n in 1..4 and every sensor count in 1..5.
CASES = [
    (11, 1, 1, False, 15),
    (12, 1, 3, False, 20),
    (13, 2, 2, False, 30),
    (14, 2, 5, True, 25),
    (15, 3, 1, True, 20),
    (16, 3, 4, False, 30),
    (17, 4, 3, False, 15),
    (18, 4, 5, True, 30),
    (19, 2, 3, False, 20),
    (20, 4, 2, True, 25),
]
IDS = [f"seed{s}-n{n}-S{S}{'-G' if g else ''}-K{K}" for s, n, S, g, K in CASES]


def _all_rows(sys: System) -> np.ndarray:
    return np.arange(sys.m)


# --------------------------------------------------------------------------------------------
# (a) CKF


@pytest.mark.parametrize(("seed", "n", "S", "with_G", "K"), CASES, ids=IDS)
def test_ckf_matches_filterpy(seed: int, n: int, S: int, with_G: bool, K: int) -> None:
    sys = random_system(seed, n, S, with_G=with_G)
    z = _data(sys, K, seed)
    ref = filterpy_all(sys, z, _all_rows(sys))
    est = estimate(sys, z, "CKF")
    assert est.shared_cov
    assert_matches(est, *ref, "CKF")


@pytest.mark.parametrize(("seed", "n", "S", "with_G", "K"), CASES[:6], ids=IDS[:6])
def test_hkf_equals_filterpy_ckf(seed: int, n: int, S: int, with_G: bool, K: int) -> None:
    """Sec. V-C: with independent sensor noise the hierarchical filter reproduces the CKF."""
    sys = random_system(seed, n, S, with_G=with_G)
    z = _data(sys, K, seed)
    ref = filterpy_all(sys, z, _all_rows(sys))
    assert_matches(estimate(sys, z, "HKF"), *ref, "HKF")


@pytest.mark.parametrize("seed", [21, 22])
@pytest.mark.parametrize("n", [1, 3])
def test_ckf_with_cross_covariance_matches_filterpy(seed: int, n: int) -> None:
    """Two sensors with mutually dependent noise: FilterPy gets the full block R."""
    sys = random_system(seed, n, 2, correlated=True)
    assert set(sys.cross_R) == {(0, 1)}
    assert np.abs(sys.cross_R[(0, 1)]).max() > 0.05
    assert np.linalg.eigvalsh(sys.R).min() > 0
    z = _data(sys, 20, seed)
    ref = filterpy_all(sys, z, _all_rows(sys))
    assert_matches(estimate(sys, z, "CKF"), *ref, "CKF (cross-covariance)")
    # The sensor-only filters see only their own block of R.
    for j, sl in enumerate(sys.sensor_slices):
        ref_j = filterpy_all(sys, z, _all_rows(sys)[sl])
        assert_matches(estimate(sys, z, f"SKF:s{j + 1}"), *ref_j, f"SKF:s{j + 1} (cross)")


def test_ckf_with_cross_covariance_differs_from_block_diagonal() -> None:
    """Guard for the test above: the cross-covariance actually changes the CKF."""
    sys = random_system(21, 3, 2, correlated=True)
    indep = System(F=sys.F, Q=sys.Q, sensors=sys.sensors, prior=sys.prior)
    z = _data(sys, 20, 21)
    a, b = estimate(sys, z, "CKF"), estimate(indep, z, "CKF")
    assert np.max(np.abs(a.cov - b.cov)) > 1e-3


# --------------------------------------------------------------------------------------------
# (b) SKF


@pytest.mark.parametrize(("seed", "n", "S", "with_G", "K"), CASES, ids=IDS)
def test_skf_matches_filterpy_on_that_sensor(seed: int, n: int, S: int, with_G: bool, K: int):
    sys = random_system(seed, n, S, with_G=with_G)
    z = _data(sys, K, seed)
    rows = _all_rows(sys)
    # Default SKF is the first sensor; SKF:<name> every sensor (non-first ones included).
    ref0 = filterpy_all(sys, z, rows[sys.sensor_slices[0]])
    assert_matches(estimate(sys, z, "SKF"), *ref0, "SKF")
    for j, sl in enumerate(sys.sensor_slices):
        ref = filterpy_all(sys, z, rows[sl])
        assert_matches(estimate(sys, z, f"SKF:s{j + 1}"), *ref, f"SKF:s{j + 1}")


@pytest.mark.parametrize(("seed", "n", "S", "with_G", "K"), CASES[:5], ids=IDS[:5])
def test_single_sensor_fusion_architectures_reduce_to_filterpy(seed, n, S, with_G, K):
    """With one sensor there is nothing to fuse: each filtering architecture is that sensor's KF."""
    sys = random_system(seed, n, S, with_G=with_G).subset([0])
    z = _data(sys, K, seed)
    ref = filterpy_all(sys, z, _all_rows(sys))
    for arch in ("CKF", "HKF", "MSC", "MSC-GMF", "CI", "SKF"):
        assert_matches(estimate(sys, z, arch), *ref, f"{arch} (one sensor)")


# --------------------------------------------------------------------------------------------
# (c) FBS


@pytest.mark.parametrize(("seed", "n", "S", "with_G", "K"), CASES, ids=IDS)
def test_fbs_matches_filterpy_rts(seed: int, n: int, S: int, with_G: bool, K: int) -> None:
    sys = random_system(seed, n, S, with_G=with_G)
    z = _data(sys, K, seed)
    ref = filterpy_all(sys, z, _all_rows(sys), smooth=True)
    est = estimate(sys, z, "FBS")
    assert est.shared_cov
    assert_matches(est, *ref, "FBS")
    # The smoother ends on the filter: the last instant is the CKF estimate.
    ckf = estimate(sys, z, "CKF")
    np.testing.assert_allclose(est.mean[:, -1], ckf.mean[:, -1], rtol=1e-9, atol=1e-9)


def test_fbs_with_cross_covariance_matches_filterpy_rts() -> None:
    sys = random_system(23, 2, 2, correlated=True)
    z = _data(sys, 25, 23)
    ref = filterpy_all(sys, z, _all_rows(sys), smooth=True)
    assert_matches(estimate(sys, z, "FBS"), *ref, "FBS (cross-covariance)")


# --------------------------------------------------------------------------------------------
# Missing measurements (NaN), different per run


def _knock_out(sys: System, z: np.ndarray, seed: int, components: bool) -> np.ndarray:
    """NaN whole sensors at random steps (and, with `components`, single components too), with a
    different pattern in every run; run 0 also loses everything at k = 0 and at one later step."""
    rng = np.random.default_rng(seed)
    z = z.copy()
    M, K1, _ = z.shape
    for r in range(M):
        for sl in sys.sensor_slices:
            drop = rng.random(K1) < 0.3
            z[r, drop, sl] = np.nan
        if components:
            z[r][rng.random((K1, sys.m)) < 0.1] = np.nan
    z[0, 0] = np.nan
    z[0, K1 // 2] = np.nan
    return z


MISSING = [
    (31, 2, 3, False, 20, False),
    (32, 3, 2, True, 25, True),
    (33, 1, 4, False, 15, True),
    (34, 4, 3, False, 30, False),
]


@pytest.mark.parametrize(("seed", "n", "S", "with_G", "K", "components"), MISSING)
def test_missing_measurements_match_filterpy(seed, n, S, with_G, K, components) -> None:
    sys = random_system(seed, n, S, with_G=with_G)
    z = _knock_out(sys, _data(sys, K, seed), seed, components)
    assert np.isnan(z).any()
    # Patterns differ between runs, so the per-run path is exercised.
    assert not np.array_equal(np.isnan(z[0]), np.isnan(z[1]))
    rows = _all_rows(sys)

    est = estimate(sys, z, "CKF")
    assert not est.shared_cov
    assert_matches(est, *filterpy_all(sys, z, rows), "CKF (missing)")

    assert_matches(estimate(sys, z, "FBS"), *filterpy_all(sys, z, rows, True), "FBS (missing)")

    j = S - 1
    ref = filterpy_all(sys, z, rows[sys.sensor_slices[j]])
    assert_matches(estimate(sys, z, f"SKF:s{j + 1}"), *ref, f"SKF:s{j + 1} (missing)")

    assert_matches(estimate(sys, z, "HKF"), *filterpy_all(sys, z, rows), "HKF (missing)")


def test_missing_measurements_with_cross_covariance_match_filterpy() -> None:
    """With dependent sensor noise, dropping one sensor leaves the other's own block of R."""
    sys = random_system(35, 2, 2, correlated=True)
    z = _knock_out(sys, _data(sys, 20, 35), 35, components=True)
    rows = _all_rows(sys)
    assert_matches(estimate(sys, z, "CKF"), *filterpy_all(sys, z, rows), "CKF (cross, missing)")
    assert_matches(
        estimate(sys, z, "FBS"), *filterpy_all(sys, z, rows, True), "FBS (cross, missing)"
    )


def test_paper_example_matches_filterpy() -> None:
    """The paper's own example (Sec. VI), all three sensors, filter and smoother."""
    sys = ajgl2009()
    z = simulate(sys, 20, 1, 0, RUNS)[1]
    rows = _all_rows(sys)
    for arch in ("CKF", "HKF"):
        assert_matches(estimate(sys, z, arch), *filterpy_all(sys, z, rows), arch)
    assert_matches(estimate(sys, z, "FBS"), *filterpy_all(sys, z, rows, True), "FBS")
    ref = filterpy_all(sys, z, rows[sys.sensor_slices[2]])
    assert_matches(estimate(sys, z, "SKF:s3"), *ref, "SKF:s3")


# --------------------------------------------------------------------------------------------
# A wider randomised sweep and the no-prior limit


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 4),
    S=st.integers(1, 5),
    with_G=st.booleans(),
    correlated=st.booleans(),
    K=st.integers(15, 30),
)
def test_random_models_ckf_skf_fbs_match_filterpy(seed, n, S, with_G, correlated, K) -> None:
    sys = random_system(seed, n, S, with_G=with_G, correlated=correlated)
    z = _data(sys, K, seed)
    rows = _all_rows(sys)
    assert_matches(estimate(sys, z, "CKF"), *filterpy_all(sys, z, rows), "CKF")
    assert_matches(estimate(sys, z, "FBS"), *filterpy_all(sys, z, rows, True), "FBS")
    j = seed % S
    ref = filterpy_all(sys, z, rows[sys.sensor_slices[j]])
    assert_matches(estimate(sys, z, f"SKF:s{j + 1}"), *ref, f"SKF:s{j + 1}")


def test_no_prior_is_the_diffuse_limit_of_filterpy() -> None:
    """Without a prior the CKF starts from zero information (the paper's example needs two
    position fixes for a covariance to exist). FilterPy started from N(0, p I) approaches it as
    p grows, with a difference shrinking like 1/p."""
    paper = ajgl2009()
    sys = System(F=paper.F, Q=paper.Q, sensors=paper.sensors, prior=None, initial=paper.prior)
    z = simulate(sys, 20, 3, 0, RUNS)[1]
    est = estimate(sys, z, "CKF")
    assert np.isnan(est.cov[0]).all() and np.isfinite(est.cov[1:]).all()
    diffs = []
    for p in (1e5, 1e6):
        diffuse = System(
            F=sys.F, Q=sys.Q, sensors=sys.sensors, prior=Prior(np.zeros(2), p * np.eye(2))
        )
        ref_mean, ref_cov = filterpy_all(diffuse, z, _all_rows(sys))
        diffs.append(
            max(
                np.max(np.abs(est.mean[:, 1:] - ref_mean[:, 1:])) / np.max(np.abs(ref_mean)),
                np.max(np.abs(est.cov[1:] - ref_cov[:, 1:])) / np.max(np.abs(ref_cov[:, 1:])),
            )
        )
    assert diffs[1] < 1e-6
    assert 5.0 < diffs[0] / diffs[1] < 20.0
