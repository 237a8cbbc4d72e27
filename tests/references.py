"""Independent references written from the paper's equations (Ajgl-Simandl-Dunik, seed 000),
for test_references_linear and test_references_exact: helpers, not tests.

* local KFs on their own sensors, their joint error covariance by eq. (35) with K_i R_ij K_j^T
  for correlated sensor noise, fused by Millman's formula (MSC, 32-34), the generalised Millman
  formula as its constrained least squares (MSC-GMF, 6-7: min tr(W Sigma W^T) subject to
  sum_i W_i = I, the KKT system), covariance intersection with the weight from the root of
  d tr P / d omega (CI, two sensors) and the plain average with the covariance it really has
  (AVG, 4: P = sum_ij P_ij / N^2);
* the hierarchical KF with feedback (36-40), the CKF and its RTS smoother;
* without a prior, information filters started from zero information (CKF, HKF, MSC);
* the exact bias and MSE matrix of any of them under any truth, by superposition;
* small random systems, irregular instants, loss masks and data for them.

Each loop is plain numpy over the runs (gains are shared by runs with the same pattern).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from conftest import random_system
from scipy.optimize import brentq

from fusionlog.core.architectures import estimate
from fusionlog.core.model import System
from fusionlog.core.simulate import simulate

K = 12
PIPELINE = Path(__file__).resolve().parents[1] / "pipeline"


# --------------------------------------------------------------------------------------------
# References written from the equations


def rows_of(system: System, j: int, present: np.ndarray) -> np.ndarray:
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
            r = rows_of(system, j, mask[k])
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
            r = rows_of(system, j, mask[k])
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
    """The means (M, K+1, n) and covariances (K+1, n, n) of `arch` (SKF:name: the CKF of that
    sensor alone)."""
    if arch.startswith("SKF:"):
        j = system.sensor_index(arch[4:])
        rows = np.arange(system.m)[system.sensor_slices[j]]
        return ckf(system.subset([j]), z[..., rows], mask[:, rows])
    if arch == "HKF":
        return hkf(system, z, mask)
    if arch in ("CKF", "FBS"):
        return ckf(system, z, mask, smooth=arch == "FBS")
    return fuse(arch, *local_filters(system, z, mask))


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
    information filters' informations and vectors summed, 32-34). Returns the means, the
    covariances Y^-1 (NaN where Y is singular to working precision, condition >= 1e12: no
    estimate) and the condition numbers of Y."""
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
    sv = np.linalg.svd(Y, compute_uv=False)  # descending
    cond = np.full(len(Y), np.inf)
    np.divide(sv[:, 0], sv[:, -1], out=cond, where=sv[:, -1] > 0)
    P = np.full_like(Y, np.nan)
    P[cond < 1e12] = np.linalg.inv(Y[cond < 1e12])
    return np.einsum("mki,kij->mkj", y, P), P, cond


def basis_runs(truth: System, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The truth (D+1, K+1, n) and measurements (D+1, K+1, m; NaN where `mask` (K+1, m) is
    False) of `exact_by_superposition`'s runs: xi = (x0, w_1..w_K, v_0..v_K) = mean + L eta,
    L = blockdiag(P_0, GQG_k, R_k)^(1/2) of the truth; run 0 has eta = 0, run i + 1 the i-th
    unit vector."""
    n, m, K1 = truth.n, truth.m, len(mask)
    init = truth.truth_initial
    D = n + (K1 - 1) * n + K1 * m
    eta = np.vstack([np.zeros(D), np.eye(D)])
    x = init.mean + eta[:, :n] @ psd_sqrt(init.cov).T
    X, Z = np.empty((D + 1, K1, n)), np.empty((D + 1, K1, m))
    off = n
    for k in range(K1):
        if k:
            x = x @ truth.F_at(k).T + eta[:, off : off + n] @ psd_sqrt(truth.GQG_at(k)).T
            off += n
        X[:, k] = x
    H = truth.linear_measurement()
    for k in range(K1):
        Z[:, k] = X[:, k] @ H.T + eta[:, off : off + m] @ psd_sqrt(truth.R_at(k)).T
        off += m
    return X, np.where(mask, Z, np.nan)


def exact_by_superposition(filt: System, truth: System, arch: str, mask: np.ndarray, ref=None):
    """Bias (K+1, n), E[e e^T] (K+1, n, n) and reported covariance of the reference estimator
    `ref(filt, arch, Z, mask)` (default `reference`; its first two results the means (runs,
    K+1, n) and covariances) built on `filt` when the data come from `truth`: the truth and
    the measurements are affine in eta (`basis_runs`), the gains do not depend on the data,
    so the error is c + A eta, E[e e^T] = c c^T + A A^T."""
    X, Z = basis_runs(truth, mask)
    mean, cov = (ref or reference)(filt, arch, Z, mask)[:2]
    e = X - mean
    c, A = e[0], e[1:] - e[0]
    return c, c[:, :, None] * c[:, None, :] + np.einsum("rki,rkj->kij", A, A), cov


# --------------------------------------------------------------------------------------------
# Systems and data


def system_of(seed: int, dims: list[int], correlated: bool = True) -> System:
    return random_system(np.random.default_rng(seed), 3, dims, correlated=correlated)


def on_irregular_instants(system: System, seed: int) -> System:
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


def mask_of(system: System, seed: int, share: float = 0.3) -> np.ndarray:
    """A pattern of present components (K+1, m): whole sensors lost with probability `share`,
    and a few single components on top."""
    rng = np.random.default_rng(seed)
    mask = np.ones((K + 1, system.m), bool)
    for sl in system.sensor_slices:
        mask[rng.random(K + 1) < share, sl] = False
    mask &= rng.random(mask.shape) > 0.1
    return mask


def data_of(system: System, mask: np.ndarray, runs: int = 4, seed: int = 7) -> np.ndarray:
    z = simulate(system, K, seed, 0, runs)[1]
    return np.where(mask, z, np.nan)


@dataclasses.dataclass
class MeanCov:
    mean: np.ndarray  # (K+1, M, n): steps first, as `sensitivity` wants them
    cov: np.ndarray  # (K+1, n, n)


def estimate_ours(arch: str, z: np.ndarray):
    def compute(system: System) -> MeanCov:
        est = estimate(system, z, arch)
        cov = est.cov if est.cov.ndim == 3 else est.cov[0]
        return MeanCov(np.swapaxes(est.mean, 0, 1), cov)

    return compute


def psd_sqrt(C: np.ndarray) -> np.ndarray:
    """A square root L L^T = C of a positive semidefinite C."""
    w, V = np.linalg.eigh(C)
    return V * np.sqrt(np.clip(w, 0.0, None))
