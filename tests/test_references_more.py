"""More independent references, written in the test from the paper's equations (Ajgl-Simandl-
Dunik, seed 000), for the cases the FilterPy references do not reach:

* the track-to-track architectures per run: local KFs on their own sensors, their joint error
  covariance by eq. (35) with K_i R_ij K_j^T for correlated sensor noise, fused by Millman's
  formula (MSC, 32-34), the generalised Millman formula as its constrained least squares
  (MSC-GMF, 6-7: min tr(W Sigma W^T) subject to sum_i W_i = I, the KKT system), covariance
  intersection with the weight from the root of d tr P / d omega (CI, two sensors) and the plain
  average with the covariance it really has (AVG, 4: P = sum_ij P_ij / N^2) -- with correlated
  sensors and lost measurements;
* the hierarchical KF with feedback (36-40) with correlated sensors (where it is not the CKF)
  and lost measurements;
* the exact analysis (`core.exact.analyse`) under model mismatch, correlated noise and lost
  measurements against the exact error statistics of these references, obtained by
  superposition: every reference is affine in (x0, w, v) with gains that do not depend on the
  data, so its error is c + A xi with xi ~ N(0, I) and E[e e^T] = c c^T + A A^T, read off by
  running the reference once on the means and once per unit noise direction.

Each loop is plain numpy over the runs (gains are shared by runs with the same pattern); the
tolerances come from the problem's own sensitivity to rounding (`conditioning`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conditioning import REL, SAFETY, assert_agree, sensitivity
from conftest import random_system
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.optimize import brentq

import fusionlog as fl
from fusionlog.core.architectures import build_plan, estimate
from fusionlog.core.exact import analyse
from fusionlog.core.model import Prior, System, ajgl2009
from fusionlog.core.models import BearingSensor, CoordinatedTurn, RangeBearingSensor
from fusionlog.core.models.polar import wrap
from fusionlog.core.nonlinear import estimate as nonlinear_estimate
from fusionlog.core.simulate import simulate

K = 12
PIPELINE = Path(__file__).resolve().parents[1] / "pipeline"


# --------------------------------------------------------------------------------------------
# References written from the equations


def _rows(system: System, j: int, present: np.ndarray) -> np.ndarray:
    """The stacked rows of sensor j that are present at this instant."""
    sl = system.sensor_slices[j]
    idx = np.arange(system.m)[sl]
    return idx[present[idx]]


def local_filters(system: System, z: np.ndarray, mask: np.ndarray):
    """Local KFs, one per sensor, without feedback, on runs z (M, K+1, m) sharing the pattern
    mask (K+1, m). Returns the local means (S, M, K+1, n) and the joint error covariance
    (K+1, S, S, n, n) of eq. (35): P_ij- = F P_ij+ F^T + G Q G^T, P_ij+ = (I - K_i H_i) P_ij-
    (I - K_j H_j)^T + K_i R_ij K_j^T (R_ij the cross-covariance of the present rows)."""
    n, S = system.n, len(system.sensors)
    H, R = system.H, system.R
    M, K1, _ = z.shape
    x = np.tile(system.prior.mean, (S, M, 1))  # (S, M, n)
    J = np.zeros((S, S, n, n))
    J[:] = system.prior.cov
    xs = np.empty((S, M, K1, n))
    Js = np.empty((K1, S, S, n, n))
    eye = np.eye(n)
    for k in range(K1):
        if k:
            F = system.F_at(k)
            x = x @ F.T
            J = F @ J @ F.T + system.GQG_at(k)
        A, G, rows = [], [], []
        for j in range(S):
            r = _rows(system, j, mask[k])
            rows.append(r)
            if r.size == 0:
                A.append(eye)
                G.append(np.zeros((n, 0)))
                continue
            Hj = H[r]
            Sj = Hj @ J[j, j] @ Hj.T + R[np.ix_(r, r)]
            Kj = np.linalg.solve(Sj, Hj @ J[j, j]).T
            x[j] = x[j] + (z[:, k, r] - x[j] @ Hj.T) @ Kj.T
            A.append(eye - Kj @ Hj)
            G.append(Kj)
        J = np.array(
            [
                [
                    A[i] @ J[i, j] @ A[j].T + G[i] @ R[np.ix_(rows[i], rows[j])] @ G[j].T
                    for j in range(S)
                ]
                for i in range(S)
            ]
        )
        xs[:, :, k] = x
        Js[k] = J
    return xs, Js


def fuse(arch: str, xs: np.ndarray, Js: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fusion rule of `arch` at every step: means (M, K+1, n), covariances (K+1, n, n)."""
    S, M, K1, n = xs.shape
    mean, cov = np.empty((M, K1, n)), np.empty((K1, n, n))
    for k in range(K1):
        J, x = Js[k], xs[:, :, k]
        Y = [np.linalg.inv(J[j, j]) for j in range(S)]
        if arch == "MSC":  # eqs. (32)-(34)
            P = np.linalg.inv(sum(Y))
            m = sum(x[j] @ Y[j] for j in range(S)) @ P
        elif arch == "MSC-GMF":  # eqs. (6)-(7) as min tr(W Sigma W^T), sum_i W_i = I
            Sigma = J.transpose(0, 2, 1, 3).reshape(S * n, S * n)
            E = np.tile(np.eye(n), (S, 1))
            KKT = np.block([[Sigma, -E], [E.T, np.zeros((n, n))]])
            rhs = np.vstack([np.zeros((S * n, n)), np.eye(n)])
            W = np.linalg.lstsq(KKT, rhs, rcond=None)[0][: S * n].T  # (n, S n)
            P = W @ Sigma @ W.T
            m = x.transpose(1, 0, 2).reshape(M, S * n) @ W.T
        elif arch == "AVG":  # eq. (4)
            P = J.sum(axis=(0, 1)) / S**2
            m = x.mean(axis=0)
        elif arch == "CI":  # two inputs: omega where d tr P / d omega = -tr(P (Y1 - Y2) P) = 0
            assert S == 2

            def P_of(w, Y=Y):
                return np.linalg.inv(w * Y[0] + (1 - w) * Y[1])

            def g(w, Y=Y):
                P = P_of(w)
                return np.trace(P @ (Y[0] - Y[1]) @ P)

            if np.abs(Y[0] - Y[1]).max() <= 1e-13 * np.abs(Y[0]).max():
                w = 0.5  # equal covariances: every omega gives P; by symmetry, the average
            elif g(0.0) <= 0:
                w = 0.0
            elif g(1.0) >= 0:
                w = 1.0
            else:
                w = brentq(g, 0.0, 1.0, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)
            P = P_of(w)
            m = (w * x[0] @ Y[0] + (1 - w) * x[1] @ Y[1]) @ P
        else:
            raise AssertionError(arch)
        mean[:, k], cov[k] = m, P
    return mean, cov


def hkf(system: System, z: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hierarchical KF with feedback, eqs. (36)-(40): the fused prediction (38) handed to
    every local KF, which updates with its own sensor believing its own R_j only; the centre
    adds the equivalent measurements P_j^-1 x_j - P^-1 x_pred (36)-(37)."""
    n, H, R = system.n, system.H, system.R
    M, K1, _ = z.shape
    x = np.repeat(system.prior.mean[None], M, axis=0)
    P = system.prior.cov.copy()
    mean, cov = np.empty((M, K1, n)), np.empty((K1, n, n))
    eye = np.eye(n)
    for k in range(K1):
        if k:
            F = system.F_at(k)
            x = x @ F.T
            P = F @ P @ F.T + system.GQG_at(k)
        Yp = np.linalg.inv(P)
        Y, y = Yp.copy(), x @ Yp
        for j in range(len(system.sensors)):
            r = _rows(system, j, mask[k])
            if r.size == 0:
                continue
            Hj, Rj = H[r], R[np.ix_(r, r)]
            Kj = np.linalg.solve(Hj @ P @ Hj.T + Rj, Hj @ P).T
            xj = x + (z[:, k, r] - x @ Hj.T) @ Kj.T
            A = eye - Kj @ Hj
            Yj = np.linalg.inv(A @ P @ A.T + Kj @ Rj @ Kj.T)
            Y += Yj - Yp
            y += xj @ Yj - x @ Yp
        P = np.linalg.inv(Y)
        x = y @ P
        mean[:, k], cov[k] = x, P
    return mean, cov


def ckf(system: System, z: np.ndarray, mask: np.ndarray, smooth: bool = False):
    """The centralised KF on the stacked present rows with their full R (29-31); `smooth`: then
    the Rauch-Tung-Striebel pass, which the forward-backward smoother (25-28) equals."""
    n, H, R = system.n, system.H, system.R
    M, K1, _ = z.shape
    x, P = np.repeat(system.prior.mean[None], M, axis=0), system.prior.cov.copy()
    mean, cov = np.empty((M, K1, n)), np.empty((K1, n, n))
    for k in range(K1):
        if k:
            F = system.F_at(k)
            x, P = x @ F.T, F @ P @ F.T + system.GQG_at(k)
        r = np.flatnonzero(mask[k])
        if r.size:
            Kg = np.linalg.solve(H[r] @ P @ H[r].T + R[np.ix_(r, r)], H[r] @ P).T
            A = np.eye(n) - Kg @ H[r]
            x = x + (z[:, k, r] - x @ H[r].T) @ Kg.T
            P = A @ P @ A.T + Kg @ R[np.ix_(r, r)] @ Kg.T
        mean[:, k], cov[k] = x, P
    if smooth:
        for k in range(K1 - 2, -1, -1):
            F = system.F_at(k + 1)
            Pp = F @ cov[k] @ F.T + system.GQG_at(k + 1)
            C = np.linalg.solve(Pp, F @ cov[k]).T
            mean[:, k] = mean[:, k] + (mean[:, k + 1] - mean[:, k] @ F.T) @ C.T
            cov[k] = cov[k] + C @ (cov[k + 1] - Pp) @ C.T
    return mean, cov


def reference(system: System, arch: str, z: np.ndarray, mask: np.ndarray):
    if arch == "HKF":
        return hkf(system, z, mask)
    if arch in ("CKF", "FBS"):
        return ckf(system, z, mask, smooth=arch == "FBS")
    return fuse(arch, *local_filters(system, z, mask))


# --------------------------------------------------------------------------------------------
# Systems and data


def _system(seed: int, dims: list[int], correlated: bool = True) -> System:
    return random_system(np.random.default_rng(seed), 3, dims, correlated=correlated)


def _irregular(system: System, seed: int) -> System:
    """`system` on irregular instants: a continuous model (A, Qc) discretised exactly for each
    interval (F_k = expm(A dt_k), Q_k by Van Loan), intervals drawn in [0.2, 1.5]."""
    rng = np.random.default_rng(seed)
    n = system.n
    A = 0.4 * rng.standard_normal((n, n)) - 0.2 * np.eye(n)
    B = rng.standard_normal((n, n))
    Qc = 0.1 * (B @ B.T / n + 0.2 * np.eye(n))
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.2, 1.5, K))])
    out = dataclasses.replace(system, continuous=(A, Qc)).on_times(times)
    assert out.Fs is not None and len(np.unique(np.diff(times))) == K
    return out


def _mask(system: System, seed: int, share: float = 0.3) -> np.ndarray:
    """A pattern of present components (K+1, m): whole sensors lost with probability `share`,
    and a few single components on top."""
    rng = np.random.default_rng(seed)
    mask = np.ones((K + 1, system.m), bool)
    for sl in system.sensor_slices:
        mask[rng.random(K + 1) < share, sl] = False
    mask &= rng.random(mask.shape) > 0.1
    return mask


def _data(system: System, mask: np.ndarray, runs: int = 4, seed: int = 7) -> np.ndarray:
    z = simulate(system, K, seed, 0, runs)[1]
    return np.where(mask, z, np.nan)


@dataclasses.dataclass
class MeanCov:
    mean: np.ndarray  # (K+1, M, n): steps first, as `sensitivity` wants them
    cov: np.ndarray  # (K+1, n, n)


def _ours(arch: str, z: np.ndarray):
    def compute(system: System) -> MeanCov:
        est = estimate(system, z, arch)
        cov = est.cov if est.cov.ndim == 3 else est.cov[0]
        return MeanCov(np.swapaxes(est.mean, 0, 1), cov)

    return compute


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


@pytest.mark.parametrize(("arch", "dims", "correlated", "lost"), CASES, ids=IDS)
def test_architecture_equals_its_equations_per_run(arch, dims, correlated, lost) -> None:
    """Means and reported covariances of every run equal the reference loop's."""
    system = _system(31 + len(dims), dims, correlated)
    mask = _mask(system, 5) if lost else np.ones((K + 1, system.m), bool)
    z = _data(system, mask)
    mean, cov = reference(system, arch, z, mask)
    compute = _ours(arch, z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    assert_agree(got.mean, np.swapaxes(mean, 0, 1), sens.tolerance("mean"), sens.unsettled, arch)
    assert_agree(got.cov, cov, sens.tolerance("cov"), sens.unsettled, arch)


@pytest.mark.parametrize("arch", ["MSC", "MSC-GMF", "CI", "AVG", "HKF"])
def test_architecture_equals_its_equations_on_irregular_instants(arch: str) -> None:
    """The same on irregular instants (a transition and a process noise per interval)."""
    dims = [2, 1] if arch == "CI" else [1, 2, 1]
    system = _irregular(_system(61, dims), 2)
    mask = _mask(system, 6)
    z = _data(system, mask)
    mean, cov = reference(system, arch, z, mask)
    compute = _ours(arch, z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    assert_agree(got.mean, np.swapaxes(mean, 0, 1), sens.tolerance("mean"), sens.unsettled, arch)
    assert_agree(got.cov, cov, sens.tolerance("cov"), sens.unsettled, arch)


def test_hkf_with_correlated_sensors_is_not_the_ckf() -> None:
    """The HKF case above is not the CKF in disguise: with correlated sensors they differ."""
    system = _system(34, [1, 2, 1])
    mask = np.ones((K + 1, system.m), bool)
    z = _data(system, mask)
    a, b = estimate(system, z, "HKF"), estimate(system, z, "CKF")
    assert np.abs(a.mean - b.mean).max() > 1e-3 * np.abs(b.mean).max()


# --------------------------------------------------------------------------------------------
# The exact analysis against the references' exact error statistics (superposition)


def _sqrt(C: np.ndarray) -> np.ndarray:
    """A square root L L^T = C of a positive semidefinite C."""
    w, V = np.linalg.eigh(C)
    return V * np.sqrt(np.clip(w, 0.0, None))


def exact_by_superposition(filt: System, truth: System, arch: str, mask: np.ndarray):
    """Bias (K+1, n) and E[e e^T] (K+1, n, n) of the reference estimator built on `filt` when
    the data come from `truth`: the truth and the measurements are affine in
    xi = (x0, w_1..w_K, v_0..v_K) = mean + L eta, eta ~ N(0, I); so is the error. Run 0 has
    eta = 0, run i + 1 the i-th unit vector."""
    n, m = truth.n, truth.m
    init = truth.truth_initial
    L0, Lv = _sqrt(init.cov), _sqrt(truth.R)
    D = n + K * n + (K + 1) * m
    eta = np.vstack([np.zeros(D), np.eye(D)])  # (D + 1, D)
    runs = D + 1
    x = init.mean + eta[:, :n] @ L0.T
    X = np.empty((runs, K + 1, n))
    Z = np.empty((runs, K + 1, m))
    off = n
    for k in range(K + 1):
        if k:
            Lw = _sqrt(truth.GQG_at(k))
            x = x @ truth.F_at(k).T + eta[:, off : off + n] @ Lw.T
            off += n
        X[:, k] = x
    for k in range(K + 1):
        Z[:, k] = X[:, k] @ truth.H.T + eta[:, off : off + m] @ Lv.T
        off += m
    Z = np.where(mask, Z, np.nan)
    mean, cov = reference(filt, arch, Z, mask)
    e = X - mean
    c, A = e[0], e[1:] - e[0]
    return c, c[:, :, None] * c[:, None, :] + np.einsum("rki,rkj->kij", A, A), cov


def _mismatched(filt: System, seed: int) -> System:
    """A truth other than the filters' model: other F, Q, R (cross-covariances too), and an
    initial state distribution other than their prior."""
    rng = np.random.default_rng(seed)
    n = filt.n
    if filt.Fs is not None:  # irregular instants: other transitions and process noises
        filt = dataclasses.replace(
            filt, Fs=filt.Fs + 0.05 * rng.standard_normal(filt.Fs.shape), Qs=3.0 * filt.Qs
        )
    sensors = tuple(dataclasses.replace(s, R=1.7 * s.R) for s in filt.sensors)
    cross = {key: 1.7 * 0.8 * v for key, v in filt.cross_R.items()}
    initial = Prior(filt.prior.mean + rng.standard_normal(n), 2.0 * filt.prior.cov)
    return dataclasses.replace(
        filt,
        F=filt.F + 0.05 * rng.standard_normal((n, n)),
        Q=3.0 * filt.Q,
        sensors=sensors,
        cross_R=cross,
        initial=initial,
    )


@dataclasses.dataclass
class Stats:
    bias: np.ndarray
    mse: np.ndarray
    nees: np.ndarray


EXACT_CASES = [
    ("CKF", [1, 2, 1], True),
    ("FBS", [1, 2, 1], True),
    ("MSC", [1, 2, 1], True),
    ("MSC-GMF", [1, 2, 1], True),
    ("MSC-GMF", [2, 2], False),
    ("AVG", [1, 2, 1], True),
    ("CI", [2, 1], True),
    ("HKF", [1, 2, 1], True),
    ("HKF", [2, 1], False),
]


@pytest.mark.parametrize(("arch", "dims", "lost"), EXACT_CASES)
@pytest.mark.parametrize("irregular", [False, True])
def test_exact_analysis_equals_superposition_under_mismatch(arch, dims, lost, irregular) -> None:
    """`analyse` of the plan with the true model = the reference's exact bias, E[e e^T] and
    NEES tr(P^-1 E[e e^T]), with a truth other than the filters' model and correlated noise,
    on regular and irregular instants."""
    filt = _system(41 + len(dims), dims)
    if irregular:
        filt = _irregular(filt, 4)
    truth = _mismatched(filt, 3)
    mask = _mask(filt, 9) if lost else np.ones((K + 1, filt.m), bool)
    bias, mse, P = exact_by_superposition(filt, truth, arch, mask)
    nees = np.einsum("kij,kji->k", np.linalg.inv(P), mse)

    def compute(system: System) -> Stats:
        ex = analyse(build_plan(system, arch, K, present=mask), truth)
        return Stats(ex.bias, ex.mse, ex.nees)

    got = compute(filt)
    sens = sensitivity(compute, filt, ("bias", "mse", "nees"))
    assert_agree(got.bias, bias, sens.tolerance("bias"), sens.unsettled, f"{arch} bias")
    assert_agree(got.mse, mse, sens.tolerance("mse"), sens.unsettled, f"{arch} mse")
    assert_agree(got.nees, nees, sens.tolerance("nees"), sens.unsettled, f"{arch} nees")


# --------------------------------------------------------------------------------------------
# The UKF against FilterPy's UnscentedKalmanFilter with MerweScaledSigmaPoints


def _radar(params: tuple[float, float, float]) -> System:
    """A range-bearing sensor 'a' and a bearing sensor 'b' of a coordinated-turn target."""
    a = RangeBearingSensor("a", np.array([0.0, 0.0]), (0, 2), 5, np.diag([25.0, 1e-3]))
    b = BearingSensor("b", np.array([900.0, 100.0]), (0, 2), 5, np.array([[4e-4]]))
    ct = CoordinatedTurn((0.1, 0.1), 1e-5)
    prior = Prior(np.array([300.0, 12.0, 400.0, -4.0, 0.04]), np.diag([100, 9, 100, 9, 1e-4]))
    F, Q = ct.jacobian(np.zeros(5), 1.0).copy(), ct.Q(1.0)
    return System(F, Q, (a, b), prior, state_names=("x", "vx", "y", "vy", "omega"),
                  motion_model=ct, filter="UKF", ukf=params)  # fmt: skip


def filterpy_ukf(system: System, z: np.ndarray, sensors: list[int]):
    """FilterPy's UKF on one run z (K+1, m) with the given sensors stacked (those that measured
    at an instant). DESIGN.md draws the update's sigma points afresh from the predicted mean and
    covariance; FilterPy's `update` would reuse the points `predict` propagated, so they are
    redrawn before each update. Angles: residuals wrapped, the mean of the images taken on
    their residuals about the central point's image."""
    n = system.n
    alpha, beta, kappa = system.ukf
    points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
    motion = system.motion
    ukf = UnscentedKalmanFilter(
        dim_x=n, dim_z=1, dt=1.0, hx=None, fx=lambda x, dt: motion.f(x, dt), points=points
    )
    ukf.x, ukf.P, ukf.Q = system.prior.mean.copy(), system.prior.cov.copy(), motion.Q(1.0)
    means, covs = [], []
    for k in range(z.shape[0]):
        if k:
            ukf.predict()
        use = [j for j in sensors if not np.isnan(z[k, system.sensor_slices[j]]).any()]
        if use:
            sens = [system.sensors[j] for j in use]
            zk = np.concatenate([z[k, system.sensor_slices[j]] for j in use])
            ang = np.concatenate([s.angles for s in sens])
            R = np.zeros((len(zk), len(zk)))
            i = 0
            for s in sens:
                R[i : i + s.dim, i : i + s.dim] = s.R
                i += s.dim

            def residual(a, b, ang=ang):
                d = np.asarray(a, float) - b
                d[ang] = wrap(d[ang])
                return d

            def z_mean(sigmas, Wm, residual=residual, ang=ang):
                c = sigmas[0] + Wm @ np.array([residual(s, sigmas[0]) for s in sigmas])
                c[ang] = wrap(c[ang])
                return c

            ukf.z_mean, ukf.residual_z = z_mean, residual
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
            ukf.update(zk, R=R, hx=lambda x, sens=sens: np.concatenate([s.h(x) for s in sens]))
        means.append(ukf.x.copy())
        covs.append(ukf.P.copy())
    return np.array(means), np.array(covs)


@pytest.mark.parametrize("params", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
@pytest.mark.parametrize("arch", ["CKF", "SKF:b"])
def test_ukf_equals_filterpy(arch: str, params) -> None:
    """The UKF local filter (CKF on both sensors, SKF on the bearing sensor) equals FilterPy's
    UnscentedKalmanFilter run by hand, per run, with lost measurements."""
    system = _radar(params)
    z = simulate(system, 15, 1, 0, 3)[1]
    lost = np.random.default_rng(1).random((3, 16, 2)) < 0.3
    for j, sl in enumerate(system.sensor_slices):
        z[:, :, sl][lost[:, :, j]] = np.nan
    est = nonlinear_estimate(system, arch, z, np.arange(16.0))
    sensors = [0, 1] if arch == "CKF" else [1]
    for r in range(z.shape[0]):
        mean, cov = filterpy_ukf(system, z[r], sensors)
        scale = np.abs(mean).max()
        np.testing.assert_allclose(est.mean[r], mean, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(est.cov[r], cov, rtol=0, atol=1e-9 * np.abs(cov).max())


# --------------------------------------------------------------------------------------------
# No prior: the information form


def information_filter(system: System, z: np.ndarray, mask: np.ndarray, groups):
    """An information filter started from Y = 0, y = 0 on runs z (M, K+1, m), updating with
    each group of rows (a list of index arrays) as if the groups' noises were independent:
    Y += H_g^T R_g^-1 H_g, y += H_g^T R_g^-1 z_g. Prediction in information form (defined for a
    singular Y): M = F^-T Y F^-1, C = M (M + Q^-1)^-1, Y- = (I - C) M, y- = (I - C) F^-T y.
    Returns Y (K+1, n, n) and y (M, K+1, n)."""
    n, M, K1 = system.n, z.shape[0], z.shape[1]
    Y, y = np.zeros((n, n)), np.zeros((M, n))
    Ys, ys = np.empty((K1, n, n)), np.empty((M, K1, n))
    eye = np.eye(n)
    for k in range(K1):
        if k:
            Fi = np.linalg.inv(system.F_at(k))
            Mk = Fi.T @ Y @ Fi
            C = Mk @ np.linalg.inv(Mk + np.linalg.inv(system.GQG_at(k)))
            Y = (eye - C) @ Mk
            Y = 0.5 * (Y + Y.T)
            y = y @ Fi @ (eye - C).T
        for g in groups:
            r = g[mask[k, g]]
            if r.size:
                Hg, Rg = system.H[r], system.R[np.ix_(r, r)]
                Y = Y + Hg.T @ np.linalg.solve(Rg, Hg)
                y = y + z[:, k, r] @ np.linalg.solve(Rg, Hg)
        Ys[k], ys[:, k] = Y, y
    return Ys, ys


def no_prior_reference(system: System, arch: str, z: np.ndarray, mask: np.ndarray):
    """CKF (one group: the full R), HKF (36-40 in information form: the fused information plus
    each sensor's equivalent measurement H_j^T R_j^-1 H_j, its own R_j only) and MSC (the local
    information filters' informations and vectors summed, 32-34)."""
    per_sensor = [np.arange(system.m)[sl] for sl in system.sensor_slices]
    if arch == "CKF":
        Y, y = information_filter(system, z, mask, [np.arange(system.m)])
    elif arch == "HKF":
        Y, y = information_filter(system, z, mask, per_sensor)
    elif arch == "MSC":
        parts = [information_filter(system, z, mask, [g]) for g in per_sensor]
        Y, y = sum(p[0] for p in parts), sum(p[1] for p in parts)
    else:
        raise AssertionError(arch)
    P = np.linalg.inv(Y)
    return np.einsum("mki,kij->mkj", y, P), P, np.linalg.cond(Y)


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC"])
@pytest.mark.parametrize(("dims", "lost"), [([1, 1, 1], False), ([1, 2], True)])
def test_no_prior_equals_the_information_form(arch: str, dims, lost: bool) -> None:
    """Without a prior, every step whose information is well conditioned (cond < 1e8) has the
    information filter's mean and covariance; ours reports no estimate only where the
    information is singular to working precision."""
    system = random_system(np.random.default_rng(50 + len(dims)), 3, dims, prior=False,
                           correlated=True)  # fmt: skip
    mask = _mask(system, 11, 0.2) if lost else np.ones((K + 1, system.m), bool)
    z = _data(system, mask)
    mean, cov, cond = no_prior_reference(system, arch, z, mask)
    compute = _ours(arch, z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    undefined = np.isnan(got.cov).any(axis=(1, 2))
    assert (cond[undefined] > 1e8).all(), arch
    use = (cond < 1e8) & ~sens.unsettled
    assert use.sum() >= K - 2
    mean_ref = np.swapaxes(mean, 0, 1)
    assert_agree(got.mean[use], mean_ref[use], sens.tolerance("mean"), None, arch)
    assert_agree(got.cov[use], cov[use], sens.tolerance("cov"), None, arch)


@pytest.mark.parametrize("arch", ["CKF", "HKF", "MSC", "MSC-GMF", "CI", "AVG", "FBS"])
def test_per_run_exact_analysis_equals_superposition_of_each_run(arch: str) -> None:
    """With a pattern per run (dropouts), the per-run plan's analysis of run r equals the
    superposition of the reference on run r's own pattern (the conditional expected values
    summary.json averages)."""
    dims = [2, 1] if arch == "CI" else [1, 2, 1]
    filt = _system(71, dims)
    truth = _mismatched(filt, 5)
    masks = np.stack([_mask(filt, 20 + r) for r in range(3)])
    ex = analyse(build_plan(filt, arch, K, present=masks), truth)
    for r in range(3):
        bias, mse, _ = exact_by_superposition(filt, truth, arch, masks[r])

        def compute(system: System, r=r) -> Stats:
            e = analyse(build_plan(system, arch, K, present=masks[r]), truth)
            return Stats(e.bias, e.mse, e.nees)

        sens = sensitivity(compute, filt, ("bias", "mse"), trials=2)
        assert_agree(ex.bias[r], bias, sens.tolerance("bias"), sens.unsettled, f"{arch} {r}")
        assert_agree(ex.mse[r], mse, sens.tolerance("mse"), sens.unsettled, f"{arch} {r}")


# --------------------------------------------------------------------------------------------
# The architectures with EKF local filters (nonlinear sensors and motion), per run


def _radar_ekf(turn: bool) -> System:
    """`_radar`'s sensors on a coordinated-turn target, or on a constant-velocity one (linear
    motion, nonlinear sensors), with EKF local filters."""
    system = dataclasses.replace(_radar((1.0, 2.0, 0.0)), filter="EKF")
    if turn:
        return system
    F1 = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q1 = 0.5 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    a, b = (dataclasses.replace(s, n=4) for s in system.sensors)
    prior = Prior(system.prior.mean[:4], system.prior.cov[:4, :4])
    return System(np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1), (a, b), prior,
                  state_names=("x", "vx", "y", "vy"), filter="EKF")  # fmt: skip


class LocalFilter:
    """One run's EKF (`ukf` None) or UKF (`ukf` = (alpha, beta, kappa)) steps, each also giving
    its linearised gain: the prediction's effective F (the Jacobian; for the UKF the statistical
    linearisation C^T P^-1, C the cross-covariance of the points and their images) and the
    update's I - K H (H the Jacobian; for the UKF Pxz^T P^-1). EKF: Jacobians at the
    prediction, Joseph update. UKF: lambda = alpha^2 (n + kappa) - n, points x, x +- columns
    of the lower Cholesky factor of (n + lambda) P drawn afresh for every step, angle means on
    residuals about the central image, P+ = P - K S K^T."""

    def __init__(self, system: System, ukf) -> None:
        self.motion, self.ukf, self.n = system.motion, ukf, system.n

    def _points(self, x, P):
        n = self.n
        alpha, beta, kappa = self.ukf
        lam = alpha**2 * (n + kappa) - n
        L = np.linalg.cholesky((n + lam) * P)
        X = np.vstack([x, x + L.T, x - L.T])
        Wm = np.full(2 * n + 1, 1 / (2 * (n + lam)))
        Wc = Wm.copy()
        Wm[0] = lam / (n + lam)
        Wc[0] = lam / (n + lam) + 1 - alpha**2 + beta
        return X, Wm, Wc

    def predict(self, x, P):
        """x-, P-, effective F, C = cov(x_{k-1}, x_k)."""
        Q = self.motion.Q(1.0)
        if self.ukf is None or self.motion.linear:
            F = self.motion.jacobian(x, 1.0)
            return self.motion.f(x, 1.0), F @ P @ F.T + Q, F, P @ F.T
        X, Wm, Wc = self._points(x, P)
        Y = np.array([self.motion.f(p, 1.0) for p in X])
        xp = Wm @ Y
        C = (Wc[:, None] * (X - x)).T @ (Y - xp)
        Pp = (Wc[:, None] * (Y - xp)).T @ (Y - xp) + Q
        return xp, Pp, np.linalg.solve(P, C).T, C

    def update(self, x, P, sensors, z):
        """x+, P+, I - K H for the stacked `sensors` measuring z."""
        R = np.zeros((len(z), len(z)))
        i = 0
        for s in sensors:
            R[i : i + s.dim, i : i + s.dim] = s.R
            i += s.dim

        def h(v):
            return np.concatenate([s.h(v) for s in sensors])

        def res(a, b):
            out, i = [], 0
            for s in sensors:
                out.append(s.residual(a[i : i + s.dim], b[i : i + s.dim]))
                i += s.dim
            return np.concatenate(out)

        eye = np.eye(self.n)
        if self.ukf is None:
            H = np.concatenate([s.jacobian(x) for s in sensors])
            Kg = np.linalg.solve(H @ P @ H.T + R, H @ P).T
            A = eye - Kg @ H
            return x + Kg @ res(z, h(x)), A @ P @ A.T + Kg @ R @ Kg.T, A
        X, Wm, Wc = self._points(x, P)
        Z = [h(p) for p in X]
        zhat = Z[0] + sum(w * res(zi, Z[0]) for w, zi in zip(Wm, Z, strict=True))
        dZ = np.array([res(zi, zhat) for zi in Z])
        S = (Wc[:, None] * dZ).T @ dZ + R
        Pxz = (Wc[:, None] * (X - x)).T @ dZ
        Kg = np.linalg.solve(S, Pxz.T).T
        H = np.linalg.solve(P, Pxz).T
        return x + Kg @ res(z, zhat), P - Kg @ S @ Kg.T, eye - Kg @ H


def nonlinear_architecture(system: System, arch: str, z: np.ndarray, ukf=None):
    """One run z (K+1, m) of `arch` with EKF (`ukf` None) or UKF locals (`LocalFilter`).
    CKF: one stacked update with the sensors that measured; FBS: the CKF and the RTS pass
    G = C P-^-1, x_s = x + G (x_s' - x-), P_s = P + G (P_s' - P-) G^T. HKF: the fused estimate
    predicted, each local updates it with its own sensor, 36-40. The others: locals without
    feedback, the joint error covariance of eq. (35) through the linearised gains,
    J_ij <- F_i J_ij F_j^T + Q, then (I - K_i H_i) J_ij (I - K_j H_j)^T, fused as in `fuse`.

    Also returns where the GMF is not determined by its equations: where the joint covariance
    is singular (its correlation matrix, unit-free, has an eigenvalue below 1e-10), the weights
    of min tr(W J W^T), sum W_i = I are not unique, and with nonlinear locals (whose estimates
    differ along the null direction, which the linearisation says they do not) each choice
    gives another mean; near singular, P itself depends on where the solver cuts the rank
    (here lstsq's rcond, ours 1e-12 of the unit-free KKT system) at the 1e-6 level."""
    lf = LocalFilter(system, ukf)
    sensors, sl = system.sensors, system.sensor_slices
    S, n = len(sensors), system.n
    eye = np.eye(n)

    def present(k, js):
        return [j for j in js if not np.isnan(z[k, sl[j]]).any()]

    def update(x, P, js, k):
        use = present(k, js)
        if not use:
            return x, P, eye
        return lf.update(
            x, P, [sensors[j] for j in use], np.concatenate([z[k, sl[j]] for j in use])
        )

    x0, P0 = system.prior.mean, system.prior.cov
    means, covs = [], []
    if arch in ("CKF", "FBS"):
        x, P, preds = x0.copy(), P0.copy(), [None]
        for k in range(z.shape[0]):
            if k:
                x, P, _, C = lf.predict(x, P)
                preds.append((x, P, C))
            x, P, _ = update(x, P, range(S), k)
            means.append(x)
            covs.append(P)
        if arch == "FBS":
            for k in range(z.shape[0] - 2, -1, -1):
                xp, Pp, C = preds[k + 1]
                G = np.linalg.solve(Pp, C.T).T
                means[k] = means[k] + G @ (means[k + 1] - xp)
                covs[k] = covs[k] + G @ (covs[k + 1] - Pp) @ G.T
        return np.array(means), np.array(covs), np.zeros(len(means), bool)
    if arch == "HKF":
        x, P = x0.copy(), P0.copy()
        for k in range(z.shape[0]):
            if k:
                x, P, _, _ = lf.predict(x, P)
            Yp = np.linalg.inv(P)
            Y, y = Yp.copy(), Yp @ x
            for j in range(S):
                xj, Pj, _ = update(x, P, [j], k)
                Yj = np.linalg.inv(Pj)
                Y, y = Y + Yj - Yp, y + Yj @ xj - Yp @ x
            P = np.linalg.inv(Y)
            x = P @ y
            means.append(x)
            covs.append(P)
        return np.array(means), np.array(covs), np.zeros(len(means), bool)
    xs = [x0.copy() for _ in range(S)]
    J = np.zeros((S, S, n, n))
    J[:] = P0
    undetermined = []
    for k in range(z.shape[0]):
        if k:
            out = [lf.predict(xs[j], J[j, j]) for j in range(S)]
            xs = [o[0] for o in out]
            Fs = [o[2] for o in out]
            Q = system.motion.Q(1.0)
            J = np.array([[Fs[i] @ J[i, j] @ Fs[j].T + Q for j in range(S)] for i in range(S)])
            for j in range(S):
                J[j, j] = out[j][1]  # each diagonal block the local's own covariance
        A = []
        for j in range(S):
            xs[j], Pj, Aj = update(xs[j], J[j, j], [j], k)
            A.append(Aj)
            J[j, j] = Pj
        for i in range(S):
            for j in range(S):
                if i != j:
                    J[i, j] = A[i] @ J[i, j] @ A[j].T
        mean, cov = fuse(arch, np.array(xs)[:, None, None, :], J[None])
        means.append(mean[0, 0])
        covs.append(cov[0])
        Sigma = J.transpose(0, 2, 1, 3).reshape(S * n, S * n)
        d = np.sqrt(np.diag(Sigma))
        undetermined.append(
            arch == "MSC-GMF" and np.linalg.eigvalsh(Sigma / np.outer(d, d))[0] < 1e-10
        )
    return np.array(means), np.array(covs), np.array(undetermined)


def _rounded(system: System, rng: np.random.Generator) -> System:
    """`system` with the prior's and the sensors' numbers changed at rounding level (a few ulps,
    `conditioning.REL`), which `conditioning.perturbed` cannot do for sensors without H."""

    def p(A):
        A = np.asarray(A, float)
        d = A * REL * rng.uniform(-1.0, 1.0, A.shape)
        return A + (0.5 * (d + d.T) if A.ndim == 2 else d)

    sensors = tuple(dataclasses.replace(s, R=p(s.R)) for s in system.sensors)
    prior = Prior(p(system.prior.mean), p(system.prior.cov))
    return dataclasses.replace(system, sensors=sensors, prior=prior, initial=None)


NONLINEAR_ARCHS = ["CKF", "FBS", "HKF", "MSC", "MSC-GMF", "CI", "AVG"]


@pytest.mark.parametrize("turn", [False, True])
@pytest.mark.parametrize("filt", ["EKF", "UKF"])
@pytest.mark.parametrize("arch", NONLINEAR_ARCHS)
def test_nonlinear_architectures_equal_their_equations_per_run(arch, filt, turn) -> None:
    """Each architecture with EKF or UKF locals equals the per-run loop written from its
    equations, with lost measurements (whole sensors). The tolerance: 1e-10, or SAFETY times
    how far rounding-level changes of the prior and R move ours or the reference (the GMF's
    joint covariance of the turn's locals is singular until the turn rate is observed, cond ~
    1e11 just after: the reference's unscaled KKT solve loses digits there; the steps where
    it is singular are not compared)."""
    system = dataclasses.replace(_radar_ekf(turn), filter=filt)
    z = simulate(system, 12, 3, 0, 3)[1]
    lost = np.random.default_rng(3).random((3, 13, 2)) < 0.3
    for j, sl in enumerate(system.sensor_slices):
        z[:, :, sl][lost[:, :, j]] = np.nan
    times = np.arange(13.0)
    est = nonlinear_estimate(system, arch, z, times)
    rng = np.random.default_rng(0)
    moved = [nonlinear_estimate(_rounded(system, rng), arch, z, times) for _ in range(3)]
    ukf = system.ukf if filt == "UKF" else None
    for r in range(z.shape[0]):
        mean, cov, undetermined = nonlinear_architecture(system, arch, z[r], ukf)
        mean[undetermined] = est.mean[r][undetermined]  # not decided by the equations
        cov[undetermined] = est.cov[r][undetermined]
        rng = np.random.default_rng(1)
        ref_moved = [nonlinear_architecture(_rounded(system, rng), arch, z[r], ukf) for _ in "ab"]
        for i, (got, ref, f) in enumerate(((est.mean[r], mean, "mean"), (est.cov[r], cov, "cov"))):
            axes = tuple(range(1, ref.ndim))  # per instant, relative to its largest entry
            scale = np.abs(ref).max(axis=axes)
            change = np.max(
                [np.abs(getattr(o, f)[r] - got).max(axis=axes) for o in moved]
                + [np.abs(o[i] - ref).max(axis=axes) for o in ref_moved],
                axis=0,
            )  # how far rounding moves ours, and the reference
            tol = np.maximum(1e-10, SAFETY * change / scale)
            err = np.abs(got - ref).max(axis=axes) / scale
            assert (err <= tol).all(), f"{arch} {f} run {r}: error {err} above {tol}"


# --------------------------------------------------------------------------------------------
# The posterior Cramer-Rao bound of a turning target with dropouts on irregular instants


def _polar_jacobian(sensor, x: np.ndarray) -> np.ndarray:
    """d[range, bearing]/dx (or the bearing's row) at x, written out: range = |d|,
    bearing = atan2(dy, dx), d = target - sensor."""
    ix, iy = sensor.idx
    dx, dy = x[ix] - sensor.position[0], x[iy] - sensor.position[1]
    r2 = dx * dx + dy * dy
    rows = {"range": [dx / np.sqrt(r2), dy / np.sqrt(r2)], "bearing": [-dy / r2, dx / r2]}
    kind = {"RangeBearingSensor": ("range", "bearing"), "BearingSensor": ("bearing",)}
    H = np.zeros((len(kind[type(sensor).__name__]), len(x)))
    for a, name in enumerate(kind[type(sensor).__name__]):
        H[a, [ix, iy]] = rows[name]
    return H


def pcrb_reference(system: System, times, truth, measurements) -> tuple[np.ndarray, float]:
    """Tichavsky-Muravchik-Nehorai (1998): J_0 = P_0^-1 + D_z(0); J_k = D22 - D21 (J_{k-1} +
    D11)^-1 D12 + D_z(k) with D11 = E[F~^T Q^-1 F~], D12 = -E[F~^T] Q^-1, D22 = Q^-1 (Q and
    F~ for each interval), D_z(k) = E[sum H~^T R^-1 H~] over the sensors that measured in each
    run (lost or unscheduled: nothing), expectations the averages over the runs."""
    M, K1, n = truth.shape
    motion = system.motion_model

    def Dz(k):
        D = np.zeros((n, n))
        for s in system.sensors:
            for r in range(M):
                if not np.isnan(measurements[s.name][r, k]).any():
                    H = _polar_jacobian(s, truth[r, k])
                    D += H.T @ np.linalg.solve(s.R, H)
        return D / M

    J = np.linalg.inv(system.truth_initial.cov) + Dz(0)
    bound, worst = [np.linalg.inv(J)], np.linalg.cond(J)
    for k in range(1, K1):
        dt = times[k] - times[k - 1]
        Qi = np.linalg.inv(motion.Q(dt))
        Fs = [motion.jacobian(truth[r, k - 1], dt) for r in range(M)]
        D11 = sum(F.T @ Qi @ F for F in Fs) / M
        D12 = -(sum(Fs) / M).T @ Qi
        J = Qi - D12.T @ np.linalg.solve(J + D11, D12) + Dz(k)
        bound.append(np.linalg.inv(J))
        worst = max(worst, np.linalg.cond(J))
    return np.array(bound), worst


def test_pcrb_of_a_turn_with_dropouts_on_irregular_instants(tmp_path) -> None:
    """summary.json's pcrb (the Python API's) equals the recursion written here on the
    simulation's own truth and lost measurements: coordinated_turn.toml with a radar losing a
    fifth of its measurements and a camera every 1.5 s (irregular instants) losing a quarter.
    The informations' condition numbers stay below 1e7 (asserted), so rounding moves the
    bound by less than 1e-9."""
    text = (PIPELINE / "coordinated_turn.toml").read_text()
    text = text.replace(
        "R = [[25.0, 0.0], [0.0, 1.0e-3]]", "dropout = 0.2\nR = [[25.0, 0.0], [0.0, 1.0e-3]]"
    )
    text = text.replace("period = 2.0", "period = 1.5\ndropout = 0.25")
    assert text.count("dropout = ") == 2
    path = tmp_path / "turn.toml"
    path.write_text(text)
    sc = fl.load(path)
    sim = fl.simulate(sc, runs=30, seed=3, steps=20)
    assert len(np.unique(np.round(np.diff(sim.times), 9))) == 2  # irregular instants
    for name in ("radar", "camera"):
        lost = np.isnan(sim.measurements[name]).any(axis=2)
        assert 0 < lost.mean() < 1, name
    summary = fl.evaluate(sc, sim, fl.estimate(sc, sim, ["CKF"])).summary
    bound, cond = pcrb_reference(sc.system, sim.times, sim.truth, sim.measurements)
    assert cond < 1e7
    per_state = np.diagonal(bound, axis1=1, axis2=2)
    want = per_state.sum(axis=1).mean() / sc.system.n
    assert summary["pcrb"]["mse"] == pytest.approx(want, rel=1e-9)
    np.testing.assert_allclose(summary["pcrb"]["mse_per_state"], per_state.mean(axis=0), rtol=1e-9)


@pytest.mark.parametrize("arch", ["MSC", "MSC-GMF", "CI", "AVG", "HKF", "FBS"])
def test_paper_example_equals_the_equations(arch: str) -> None:
    """The paper's example (ajgl2009: the locals share the prior and the process noise, so the
    generalised Millman system is singular; two sensors, where CI's reference is exact), with
    lost measurements."""
    system = ajgl2009(n_sensors=2)
    mask = np.ones((K + 1, system.m), bool)
    mask[np.random.default_rng(8).random(K + 1) < 0.3, 0] = False
    z = _data(system, mask)
    mean, cov = reference(system, arch, z, mask)
    compute = _ours(arch, z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    assert_agree(got.mean, np.swapaxes(mean, 0, 1), sens.tolerance("mean"), sens.unsettled, arch)
    assert_agree(got.cov, cov, sens.tolerance("cov"), sens.unsettled, arch)


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
    system = _system(3, [1, 2, 1])
    mask = _mask(system, 4)
    z = _data(system, mask)
    ref = estimate(system, z, arch)
    sens = sensitivity(_ours(arch, z), system, ("mean", "cov"))
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
        system = _irregular(system, 8)
    mask = _mask(system, 12, 0.2)
    if not prior:
        system = dataclasses.replace(system, initial=Prior(np.zeros(3), np.eye(3)))
    z = _data(system, mask)
    mean, cov, cond = batch_smoother(system, z, mask)
    assert cond < 1e10
    compute = _ours("FBS", z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    assert_agree(got.mean, np.swapaxes(mean, 0, 1), sens.tolerance("mean"), sens.unsettled, "FBS")
    assert_agree(got.cov, cov, sens.tolerance("cov"), sens.unsettled, "FBS")


def _basis_runs(truth: System, mask: np.ndarray):
    """The truth and measurements of `exact_by_superposition`'s runs: run 0 at the means, run
    i + 1 with the i-th unit noise direction (x0, w_1..w_K, v_0..v_K)."""
    n, m = truth.n, truth.m
    init = truth.truth_initial
    L0, Lv = _sqrt(init.cov), _sqrt(truth.R)
    D = n + K * n + (K + 1) * m
    eta = np.vstack([np.zeros(D), np.eye(D)])
    x = init.mean + eta[:, :n] @ L0.T
    X, Z = np.empty((D + 1, K + 1, n)), np.empty((D + 1, K + 1, m))
    off = n
    for k in range(K + 1):
        if k:
            x = x @ truth.F_at(k).T + eta[:, off : off + n] @ _sqrt(truth.GQG_at(k)).T
            off += n
        X[:, k] = x
    for k in range(K + 1):
        Z[:, k] = X[:, k] @ truth.H.T + eta[:, off : off + m] @ Lv.T
        off += m
    return X, np.where(mask, Z, np.nan)


def gmf_of_information_vectors(system: System, z: np.ndarray, mask: np.ndarray):
    """MSC-GMF without a prior from its definition: the locals are information filters whose
    vectors are y_j = Y_j x + eps_j; the joint covariance of the eps_j (exactly, by
    superposition: eps is linear in the noises) and the constraint sum_j W_j Y_j = I give the
    best linear unbiased combination x = sum_j W_j y_j, P = W Sigma W^T (min tr P, solved on
    the null space of the constraint). NaN where the constraint cannot be met."""
    groups = [np.arange(system.m)[sl] for sl in system.sensor_slices]
    X, Zb = _basis_runs(system, mask)
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
    mask = _mask(system, 13, 0.2)
    z = _data(system, mask)
    mean, cov = gmf_of_information_vectors(system, z, mask)
    compute = _ours("MSC-GMF", z)
    got = compute(system)
    sens = sensitivity(compute, system, ("mean", "cov"))
    both = ~np.isnan(cov).any(axis=(1, 2)) & ~np.isnan(got.cov).any(axis=(1, 2))
    assert both.sum() >= K - 2
    assert_agree(got.mean[both], np.swapaxes(mean, 0, 1)[both], sens.tolerance("mean"),
                 sens.unsettled[both], "mean")  # fmt: skip
    assert_agree(got.cov[both], cov[both], sens.tolerance("cov"), sens.unsettled[both], "cov")
