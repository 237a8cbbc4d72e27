"""The local filters, EKF and UKF, batched over runs: means (M, n), covariances (M, n, n).

EKF (DESIGN.md): the models linearised at the prediction (analytic Jacobians), the update in
Joseph form  P+ = (I - K H) P (I - K H)^T + K R K^T.

UKF: the scaled unscented transform (Julier 2002; Wan and van der Merwe 2000):
lambda = alpha^2 (n + kappa) - n, sigma points x, x +- columns of the lower Cholesky factor of
(n + lambda) P; weights W0m = lambda/(n+lambda), W0c = W0m + 1 - alpha^2 + beta,
Wi = 1/(2(n+lambda)). The points are drawn afresh from the predicted mean and covariance for each
update; the weighted mean of angle components is taken on residuals about the central point's
image, wrapped; the update is x+ = x + K (z - z_hat), P+ = P - K S K^T with K = Pxz S^-1.

Every difference of two measurements is the sensor model's `residual` (a bearing's wrapped to
(-pi, pi]): the one place that knows which components are angles.

Both report the *linearised gain* of an update: K and the effective H (the Jacobian for the EKF,
the statistical linearisation Pxz^T P^-1 for the UKF) and of a prediction the effective F, which
the architectures that carry cross-covariances (MSC-GMF, AVG) propagate errors through.

A run without a measurement (NaN: not scheduled, or lost) has its rows' H and innovation zeroed:
its K columns are then exactly zero (S is block-diagonal between present and absent rows), so one
batched update serves runs with any pattern of missing data.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any

import numpy as np

from ...errors import NumericalError
from ..kernels import lanes, many_matrices, unlanes
from ..linalg import mm, mT, solve, sym
from ..model import System
from ..models import LinearMotion, MotionModel, SensorModel
from .lanes import gain_lanes, joseph_update, linear_prediction


@dataclass(frozen=True)
class Stacked:
    """Several sensors as one measurement z = [h_1(x); ...; h_S(x)] (eq. 30: the CKF's one
    update per instant with every sensor that measures then); R block-diagonal, or `noise`
    where the instant has its own (a recorded log's per-message covariances, `System.Rs`)."""

    sensors: tuple[SensorModel, ...]
    noise: np.ndarray | None = field(default=None, compare=False)

    @cached_property
    def dim(self) -> int:
        return sum(s.dim for s in self.sensors)

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """z - z_hat (..., m), each sensor's asked of its model (bearings wrapped)."""
        out, start = [], 0
        for s in self.sensors:
            sl = slice(start, start + s.dim)
            out.append(s.residual(z[..., sl], z_hat[..., sl]))
            start += s.dim
        return np.concatenate(out, axis=-1)

    @cached_property
    def R(self) -> np.ndarray:
        if self.noise is not None:
            return self.noise
        R, start = np.zeros((self.dim, self.dim)), 0
        for s in self.sensors:
            R[start : start + s.dim, start : start + s.dim] = s.R
            start += s.dim
        return R

    def h(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([s.h(x) for s in self.sensors], axis=-1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([s.jacobian(x) for s in self.sensors], axis=-2)

    def linearised(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """`SensorModel.linearised` of the stack: h (m, M), the Jacobian's columns q
        (m, |q|, M) and q, the state columns some sensor's Jacobian is nonzero on."""
        parts = [s.linearised(x) for s in self.sensors]
        h = np.concatenate([p[0] for p in parts]) if len(parts) > 1 else parts[0][0]
        cols = sorted({c for p in parts for c in p[2]})
        if all(list(p[2]) == cols for p in parts):
            Hq = np.concatenate([p[1] for p in parts]) if len(parts) > 1 else parts[0][1]
        else:
            Hq, start = np.zeros((self.dim, len(cols), x.shape[0])), 0
            for _, J, c in parts:
                Hq[start : start + len(J), [cols.index(i) for i in c]] = J
                start += len(J)
        nonzero = np.flatnonzero(Hq.any(axis=(0, 2))).tolist()
        if len(nonzero) < len(cols):
            Hq, cols = np.ascontiguousarray(Hq[:, nonzero]), [cols[a] for a in nonzero]
        return h, Hq, cols


def stacked(system: System, which: list[int], k: int) -> Stacked:
    """The sensors `which` of `system` (on its instants) as one measurement at instant k, with
    R of that instant where it varies (`System.Rs`: the rows and columns of those sensors)."""
    model = Stacked(tuple(system.sensors[j] for j in which))
    if system.Rs is None:
        return model
    slices = system.sensor_slices
    rows = np.concatenate([np.arange(system.m)[slices[j]] for j in which])
    return Stacked(model.sensors, system.Rs[k][np.ix_(rows, rows)])


def transition(system: System, k: int) -> tuple[MotionModel, float]:
    """The motion model and interval from instant k-1 to k of a system on its instants
    (`System.on_times`): a linear one with that interval's F and Q, or the nonlinear model."""
    if system.motion_model is None:
        return LinearMotion(system.F_at(k), system.GQG_at(k), 1.0), 1.0
    return system.motion_model, system.dt_at(k)


def ukf_params(system: System) -> UkfParams | None:
    """The UKF's parameters of a system whose filter is the UKF, else None (the EKF)."""
    return UkfParams(*system.ukf) if system.filter == "UKF" else None


@dataclass(frozen=True)
class UkfParams:
    """[estimate.ukf]: alpha, beta, kappa (defaults 1, 2, 0)."""

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def weights(self, n: int) -> tuple[float, np.ndarray, np.ndarray]:
        """(n + lambda, Wm, Wc) for 2n + 1 sigma points; n + lambda > 0 is checked on load."""
        lam = self.alpha**2 * (n + self.kappa) - n
        c = n + lam
        Wm = np.full(2 * n + 1, 0.5 / c)
        Wc = Wm.copy()
        Wm[0] = lam / c
        Wc[0] = lam / c + 1.0 - self.alpha**2 + self.beta
        return c, Wm, Wc


class Update:
    """The result of an update: x+, P+, and the linearised gain (K, effective H). K and H may
    be given as functions that make them: the CKF never asks for either."""

    __slots__ = ("x", "P", "_K", "_H")

    def __init__(self, x: np.ndarray, P: np.ndarray, K: Any, H: Any) -> None:
        self.x, self.P = x, P
        self._K = K  # (M, n, m)
        self._H = H  # (M, m, n)

    @property
    def K(self) -> np.ndarray:
        if callable(self._K):
            self._K = self._K()
        return self._K

    @property
    def H(self) -> np.ndarray:
        if callable(self._H):
            self._H = self._H()
        return self._H


def sigma_points(x: np.ndarray, P: np.ndarray, c: float, what: str) -> np.ndarray:
    """(M, 2n+1, n): x, x + L_i, x - L_i with L L^T = c P (lower Cholesky)."""
    try:
        L = np.linalg.cholesky(c * sym(P))
    except np.linalg.LinAlgError:
        raise NumericalError(
            f"UKF: {what} is not positive definite (no sigma points); try the EKF or a "
            "larger process noise"
        ) from None
    cols = mT(L)  # (M, n, n): row i is column i of L
    return np.concatenate([x[:, None], x[:, None] + cols, x[:, None] - cols], axis=1)


def predict(
    motion: MotionModel, dt: float, x: np.ndarray, P: np.ndarray, ukf: UkfParams | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x-, P- and the effective F and the cross-covariance C = cov(x_{k-1}, x_k) (the RTS
    smoother's) of one prediction over dt. Linear motion: F x, F P F^T + Q for both filters
    (the unscented transform is exact there)."""
    Q = motion.Q(dt)
    if motion.linear and many_matrices(x.shape[:1]):  # one F for every run: on lanes
        F = motion.F(dt)
        Pp, C = linear_prediction(P, F, Q)
        return x @ F.T, Pp, F, C
    if motion.linear:  # a few runs: numpy's products, a call each (lanes make ~n^2)
        F = motion.F(dt)
        C = P @ F.T
        return x @ F.T, sym(F @ C + Q), F, C
    if ukf is None:
        F = motion.jacobian(x, dt)
        C = mm(P, mT(F))
        return motion.f(x, dt), sym(mm(F, C) + Q), F, C
    n = x.shape[-1]
    c, Wm, Wc = ukf.weights(n)
    X = sigma_points(x, P, c, "the covariance before a prediction")
    Y = motion.f(X, dt)
    xp = np.einsum("j,mjn->mn", Wm, Y)
    dY = Y - xp[:, None]
    dX = X - x[:, None]
    Pp = sym(np.einsum("j,mja,mjb->mab", Wc, dY, dY) + Q)
    C = np.einsum("j,mja,mjb->mab", Wc, dX, dY)
    F = mT(solve(P, C, hermitian=True))  # statistical linearisation: C = P F^T
    return xp, Pp, F, C


def _masked(z: np.ndarray, model: Stacked) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(present (M, m), z with NaN as 0, R with no coupling between present and absent rows)."""
    present = ~np.isnan(z)
    R = model.R
    if present.all():  # the usual case: R shared by the runs
        return present, z, R
    Rm = np.where(present[:, :, None] == present[:, None, :], R, 0.0)
    return present, np.where(present, z, 0.0), Rm


def _gain(P_xz: np.ndarray, S: np.ndarray) -> np.ndarray:
    """K = Pxz S^-1 as a solve with S (symmetric positive definite)."""
    return mT(solve(S, mT(P_xz), hermitian=True, what="the innovation covariance"))


def update_ekf(
    model: Stacked, x: np.ndarray, P: np.ndarray, z: np.ndarray, work: dict | None = None
) -> Update:
    """EKF update at the prediction, Joseph form (module docstring), on lanes and over the
    state columns the Jacobian touches (`lanes.joseph_update`, its workspace `work`)."""
    present, z0, R = _masked(z, model)
    h, Hq, q = model.linearised(x)
    y = model.residual(z0, h.T)
    if not present.all():
        Hq, y = Hq * present.T[:, None], y * present
    if not many_matrices(x.shape[:1]):
        H = np.zeros((x.shape[0], Hq.shape[0], x.shape[1]))
        H[:, :, q] = unlanes(Hq)
        return _joseph_few(x, P, H, R, y)
    if R.ndim == 3:
        R = lanes(R)
    Pl = lanes(P)
    xu, Pu, V = joseph_update(x, Pl, Hq, q, R, np.ascontiguousarray(y.T), work)

    def full_H() -> np.ndarray:
        H = np.zeros((x.shape[0], Hq.shape[0], x.shape[1]))
        H[:, :, q] = unlanes(Hq)
        return H

    return Update(xu, unlanes(Pu), lambda: unlanes(gain_lanes(Pl, q, V)).swapaxes(1, 2), full_H)


def _joseph_few(x: np.ndarray, P: np.ndarray, H: np.ndarray, R: np.ndarray, y: np.ndarray):
    """`update_ekf` of a few runs (below the lanes' `kernels.KERNEL_MIN_BATCH`; a long log's
    one): the Joseph form of the module docstring with numpy's stacked products, a call per
    product where the lanes make one per entry. H (M, m, n), R (m, m) or (M, m, m), y (M, m)."""
    PHt = P @ mT(H)
    S = H @ PHt + R
    K = mT(solve(S, mT(PHt), hermitian=True, what="the innovation covariance"))
    A = _eye(x.shape[1]) - K @ H
    Pu = sym(A @ P @ mT(A) + K @ R @ mT(K))
    return Update(x + (K @ y[..., None])[..., 0], Pu, K, H)


@lru_cache(maxsize=16)
def _eye(n: int) -> np.ndarray:
    return np.eye(n)


def update_ukf(
    model: Stacked, x: np.ndarray, P: np.ndarray, z: np.ndarray, ukf: UkfParams
) -> Update:
    """UKF update with sigma points drawn from (x, P) (module docstring)."""
    present, z0, R = _masked(z, model)
    n = x.shape[-1]
    c, Wm, Wc = ukf.weights(n)
    X = sigma_points(x, P, c, "the predicted covariance")
    Z = model.h(X)  # (M, 2n+1, m)
    # the weighted mean about the central point's image: angles averaged as wrapped residuals
    # (z_hat itself need not be wrapped: it enters only through residuals)
    D = model.residual(Z, Z[:, :1])
    zhat = Z[:, 0] + np.einsum("j,mjk->mk", Wm, D)
    dZ = model.residual(Z, zhat[:, None]) * present[:, None]
    dX = X - x[:, None]
    S = sym(np.einsum("j,mja,mjb->mab", Wc, dZ, dZ) + R)
    Pxz = np.einsum("j,mja,mjb->mab", Wc, dX, dZ)
    K = _gain(Pxz, S)
    y = model.residual(z0, zhat) * present
    Pu = sym(P - mm(mm(K, S), mT(K)))
    H = mT(solve(P, Pxz, hermitian=True))  # statistical linearisation: Pxz = P H^T
    return Update(x + np.einsum("mij,mj->mi", K, y), Pu, K, H)


def update(
    model: Stacked,
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    ukf: UkfParams | None,
    work: dict | None = None,
) -> Update:
    """One update with the sensors of `model` (z (M, m), NaN = absent): EKF when `ukf` is None
    (`work`: its workspace, kept by the caller from one instant to the next)."""
    if ukf is None:
        return update_ekf(model, x, P, z, work)
    return update_ukf(model, x, P, z, ukf)


def select(mask: np.ndarray, a, b):
    """The state `a` in the runs `mask` (M,), `b` elsewhere, for states made of arrays whose
    first axis is the run (tuples and lists of them, None kept)."""
    if mask.all():
        return a
    if a is None:
        return None
    if isinstance(a, (tuple, list)):
        return type(a)(select(mask, u, v) for u, v in zip(a, b, strict=True))
    return np.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
