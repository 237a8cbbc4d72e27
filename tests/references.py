"""Independent references written from the paper's equations (Ajgl-Simandl-Dunik, seed 000),
for test_references_linear and test_references_exact: helpers, not tests.

* local KFs on their own sensors, their joint error covariance by eq. (35) with K_i R_ij K_j^T
  for correlated sensor noise, fused by Millman's formula (MSC, 32-34), the generalised Millman
  formula as its constrained least squares (MSC-GMF, 6-7: min tr(W Sigma W^T) subject to
  sum_i W_i = I, the KKT system), covariance intersection with the weight from the root of
  d tr P / d omega (CI, two sensors) and the plain average with the covariance it really has
  (AVG, 4: P = sum_ij P_ij / N^2);
* the hierarchical KF with feedback (36-40), the CKF and its RTS smoother;
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
    if arch == "HKF":
        return hkf(system, z, mask)
    if arch in ("CKF", "FBS"):
        return ckf(system, z, mask, smooth=arch == "FBS")
    return fuse(arch, *local_filters(system, z, mask))


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
