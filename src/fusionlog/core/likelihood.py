"""The log-likelihood of the measurements through the filter's innovations (the prediction-error
decomposition: Schweppe 1965; Harvey 1989, "Forecasting, structural time series models and the
Kalman filter", sec. 3.4):

    log p(z_0, ..., z_K) = sum_k log N(nu_k; 0, S_k)
                         = -1/2 sum_k [ log det S_k + nu_k' S_k^-1 nu_k + d_k log 2 pi ],

nu_k = z_k - H x_k^- the innovation of the components present at instant k (d_k of them) and
S_k = H P_k^- H' + R_k its covariance, from the Kalman filter of eqs. (14)-(18) started at the
prior (x_0^- = mean, P_0^- = cov). Exact for a linear Gaussian model, whatever the instants
(a transition and process noise per interval), the rates (a sensor absent at an instant has no
row there), the lost readings (NaN rows skipped) and the cross-covariances between sensors (R
the block matrix of eq. 31). For nonlinear sensors or motion the same sum over the extended
Kalman filter's innovations (linearised at the prediction, Joseph update) is the usual
approximation of the likelihood (the EKF's).

The truth, where a log has it, is one more measurement of the states it gives, without noise:
the likelihood of (z, x) then factors as p(x_0) prod p(x_k | x_{k-1}) p(z_k | x_k), i.e. the
process noise is judged on the true state increments and the prior on x_0 (`truth_rows`).

Candidates: the noise covariances (Q, R, the prior's covariance) of C models at once, each an
array with a leading candidate axis, so that the finite-difference gradient and Hessian of an
optimiser are one pass over the data (the model's F and H are shared). Runs are taken in blocks
of runs; runs of a block that share their pattern of present readings share the covariance
recursion (one per candidate), otherwise each run has its own.

Absent components are zeroed as in `core.nis`: their rows of H and of nu are zero and S gets a
unit diagonal there, which adds nothing to log det S or the quadratic form and makes the gain's
columns of those rows exactly zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .architectures.estimates import shared_pattern
from .likelihood_one import loglik_one_run
from .linalg import mT, sym
from .model import System

__all__ = ["Noise", "loglik"]

LOG_2PI = float(np.log(2.0 * np.pi))

#: Entries of the per-run temporaries of one block (candidates x runs x state^2): a block of
#: runs stays a few tens of megabytes whatever the number of runs or candidates.
BLOCK_ENTRIES = 1 << 21


@dataclass(frozen=True)
class Noise:
    """The noise covariances of C candidate models.

    `P0` (C, n, n) the prior's covariance; `Q` (C, U, n, n) the process noise (state space,
    G Q G') of the U distinct intervals, `q_at` (K,) the row of Q of the interval before
    instant k = 1..K; `R` (C, V, m, m) the stacked measurement noise (eq. 31) of V distinct
    instants, `r_at` (K+1,) the row of R at each instant."""

    P0: np.ndarray
    Q: np.ndarray
    q_at: np.ndarray
    R: np.ndarray
    r_at: np.ndarray

    @property
    def candidates(self) -> int:
        return self.P0.shape[0]


def loglik(
    system: System,
    z: np.ndarray,
    noise: Noise,
    truth: np.ndarray | None = None,
    truth_rows: np.ndarray | None = None,
) -> np.ndarray:
    """The log-likelihood (C,) of the readings z (M, K+1, m) (NaN: absent) under each
    candidate's noise, pooled over the runs (a sum: the runs are independent). `system` gives
    F (or f), H (or h), the prior's mean and the instants' intervals (`System.on_times`).
    With `truth` (M, K+1, t) of the states `truth_rows` (t,), NaN where absent, the joint
    likelihood of readings and truth. A candidate whose S is not positive definite somewhere
    (or not finite) gets -inf."""
    if system.prior is None:
        raise ValueError("the likelihood needs the prior's mean and covariance")
    if truth is not None:
        z = np.concatenate([z, truth], axis=-1)
    rows = np.arange(system.n) if truth_rows is None else np.asarray(truth_rows, dtype=int)
    M, _, m = z.shape
    C, n = noise.candidates, system.n
    if M == 1 and system.linear:  # one recorded run: the lean loop of `likelihood_one`
        truth_rows = rows if truth is not None else None
        R = noise.R
        if truth is not None:  # the truth's rows: no noise
            R = np.zeros(R.shape[:2] + (m, m))
            R[..., : system.m, : system.m] = noise.R
        try:
            return loglik_one_run(
                system, z[0], noise.P0, noise.Q, noise.q_at, R, noise.r_at,
                _stacked_H(system, truth_rows), _cholesky,
            )  # fmt: skip
        except np.linalg.LinAlgError:  # a singular S: the general path names the candidates
            pass
    per_run = C * (n + m) ** 2
    B = max(1, min(M, BLOCK_ENTRIES // per_run))
    total = np.zeros(C)
    for a in range(0, M, B):
        total += _block(system, z[a : a + B], noise, rows if truth is not None else None)
    return total


def _block(system: System, z: np.ndarray, noise: Noise, truth_rows) -> np.ndarray:
    """The log-likelihood (C,) of one block of runs z (B, K+1, m [+ t])."""
    B, K1, m_all = z.shape
    C, n, m = noise.candidates, system.n, system.m
    linear = system.linear
    present = ~np.isnan(z)
    shared = shared_pattern(z) if linear else None
    pattern = present if shared is None else shared[None]  # (Mp, K+1, m_all)
    x = np.broadcast_to(system.prior.mean, (C, B, n)).copy()
    P = np.broadcast_to(noise.P0[:, None], (C, 1 if shared is not None else B, n, n)).copy()
    H_all = _stacked_H(system, truth_rows) if linear else None
    one_R = noise.R.shape[1] == 1
    steps = _Steps(pattern, H_all, _R_block(noise, 0, m, m_all) if one_R else None)
    count = present.sum(axis=(0, 2))  # readings per instant
    ll = np.zeros(C)
    bad = np.zeros(C, dtype=bool)
    counted = 0
    for k in range(K1):
        if k > 0:
            Qk = noise.Q[:, noise.q_at[k - 1], None]  # (C, 1, n, n)
            if linear:
                F = system.F_at(k)
                x = x @ F.T
                P = F @ P @ F.T + Qk
            else:
                F = _motion_jacobian(system, x, k)  # at the filtered mean, before moving it
                x = system.propagate(x, k)
                P = F @ P @ mT(F) + Qk
        step = steps.at(k)
        if step is None:
            continue
        rows, H, keep, Rm, Ht = step
        if Rm is None:
            Rm = steps.masked_R(_R_block(noise, k, m, m_all), k)
        if linear:
            nu = z[:, k, rows] - x @ Ht  # (C, B, r)
        else:
            pred, J = _predicted(system, x, truth_rows)
            H = J[..., rows, :] * keep[..., None]  # (C, B, r, n)
            nu = _residual(system, np.nan_to_num(z[:, k]), pred, m)[..., rows]
        if steps.partial[k]:
            nu = np.where(present[:, k, rows], nu, 0.0)
        PHt = P @ mT(H)
        S = H @ PHt + Rm
        L, failed = _cholesky(S)
        bad |= failed
        Linv = np.linalg.solve(L, np.eye(L.shape[-1]))
        u = _apply(Linv, nu)  # S^-1/2 nu, (C, B, r)
        logdet = np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=(1, 2))
        ll -= 0.5 * np.einsum("cbr,cbr->c", u, u) + (B / L.shape[1]) * logdet
        counted += int(count[k])
        # K = P H' S^-1 through the factor (K' = L'^-1 L^-1 H P); P+ = P - K S K' = P - P H' K'
        Kt = mT(Linv) @ (Linv @ mT(PHt))  # (C, Mp, r, n)
        x = x + _apply(mT(Kt), nu)
        P = sym(P - PHt @ Kt)
    ll -= 0.5 * LOG_2PI * counted
    ll[bad | ~np.isfinite(ll)] = -np.inf
    return ll


class _Steps:
    """What each instant's update needs of the pattern of present readings, worked out once:
    the rows some run has, the masked H (Mp, r, n) (linear models), the presence as floats
    (Mp, r), whether some run lacks a row; and, when R is the same at
    every instant, the masked R (C, Mp, r, r) per distinct pattern."""

    def __init__(self, pattern: np.ndarray, H_all: np.ndarray | None, R: np.ndarray | None):
        self.pattern, self.H_all, self.R = pattern, H_all, R
        # some run lacks a row another run has (only when runs differ)
        self.partial = (pattern.any(axis=0) & ~pattern.all(axis=0)).any(axis=-1)
        self._cache: dict[bytes, tuple] = {}

    def at(self, k: int):
        p = self.pattern[:, k]
        if not p.any():
            return None
        key = np.packbits(p).tobytes() if p.shape[0] == 1 else None
        if key is not None and key in self._cache:
            return self._cache[key]
        rows = np.flatnonzero(p.any(axis=0))
        keep = p[:, rows].astype(float)  # (Mp, r)
        H = Ht = None
        if self.H_all is not None:
            H, Ht = self.H_all[rows] * keep[..., None], self.H_all[rows].T.copy()
        Rm = None if self.R is None else self._mask(self.R, rows, keep)
        out = (rows, H, keep, Rm, Ht)
        if key is not None:
            self._cache[key] = out
        return out

    def masked_R(self, R: np.ndarray, k: int) -> np.ndarray:
        rows, _, keep, _, _ = self.at(k)
        return self._mask(R, rows, keep)

    @staticmethod
    def _mask(R: np.ndarray, rows: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """R (C, m, m) on `rows`, with the absent ones' rows and columns replaced by the
        identity's: (C, Mp, r, r)."""
        Rr = R[:, None][..., rows[:, None], rows]
        eye = np.eye(len(rows))
        return Rr * (keep[..., :, None] * keep[..., None, :]) + eye * (1.0 - keep)[..., None, :]


def _apply(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A v for maps A (C, Mp, p, q) and vectors v (C, B, q): one product per candidate when
    the runs share the map (Mp = 1; a stacked product of B tiny matrices costs B times more),
    one per run otherwise. (C, B, p)."""
    if A.shape[1] == 1:
        return v @ mT(A[:, 0])
    return (A @ v[..., None])[..., 0]


def _stacked_H(system: System, truth_rows) -> np.ndarray:
    """H of eq. (30), with the truth's rows (the identity's rows of its states) below it."""
    H = system.linear_measurement()
    if truth_rows is None:
        return H
    return np.vstack([H, np.eye(system.n)[truth_rows]])


def _R_block(noise: Noise, k: int, m: int, m_all: int) -> np.ndarray:
    """R (C, m_all, m_all) at instant k: the sensors' R, zero for the truth's rows."""
    R = noise.R[:, noise.r_at[k]]
    if m_all == m:
        return R
    out = np.zeros((R.shape[0], m_all, m_all))
    out[:, :m, :m] = R
    return out


def _motion_jacobian(system: System, x: np.ndarray, k: int) -> np.ndarray:
    """dF/dx at the filtered means x (C, B, n) over the interval before instant k."""
    if system.motion_model is None:
        return np.broadcast_to(system.F_at(k), x.shape[:-1] + (system.n, system.n))
    return system.motion_model.jacobian(x, system.dt_at(k))


def _predicted(system: System, x: np.ndarray, truth_rows) -> tuple[np.ndarray, np.ndarray]:
    """The predicted readings h(x) (C, B, m_all) and their Jacobian (C, B, m_all, n) at x."""
    h, J = system.h(x), system.jacobian(x)
    if truth_rows is None:
        return h, J
    eye = np.eye(system.n)[truth_rows]
    h = np.concatenate([h, x[..., truth_rows]], axis=-1)
    return h, np.concatenate([J, np.broadcast_to(eye, J.shape[:-2] + eye.shape)], axis=-2)


def _residual(system: System, z: np.ndarray, pred: np.ndarray, m: int) -> np.ndarray:
    """z - h(x) with each sensor's own residual (angles wrapped); the truth's rows plain."""
    head = system.residual(np.broadcast_to(z[..., :m], pred[..., :m].shape), pred[..., :m])
    return np.concatenate([head, z[..., m:] - pred[..., m:]], axis=-1)


def _cholesky(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of S (C, Mp, r, r) and the candidates (C,) with one that is not
    positive definite or not finite (their S replaced by the identity, their likelihood -inf)."""
    try:  # the usual case: one call (a non-finite S gives a non-finite likelihood, -inf)
        return np.linalg.cholesky(S), np.zeros(S.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    ok = np.isfinite(S).all(axis=(-2, -1))
    S = np.where(ok[..., None, None], S, np.eye(S.shape[-1]))
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        # which matrices the factorisation itself refuses: a smallest eigenvalue of a few ulps
        # above 0 still fails Cholesky under some BLAS kernels (OPENBLAS_CORETYPE=Prescott)
        ok &= _factorable(S.reshape(-1, *S.shape[-2:])).reshape(ok.shape)
        L = np.linalg.cholesky(np.where(ok[..., None, None], S, np.eye(S.shape[-1])))
    failed = ~ok.reshape(ok.shape[0], -1).all(axis=1)
    return L, failed


def _factorable(S: np.ndarray) -> np.ndarray:
    """Whether each matrix of S (N, r, r) has a Cholesky factor (rare path: one call each)."""
    good = np.ones(S.shape[0], dtype=bool)
    for i, s in enumerate(S):
        try:
            np.linalg.cholesky(s)
        except np.linalg.LinAlgError:
            good[i] = False
    return good
