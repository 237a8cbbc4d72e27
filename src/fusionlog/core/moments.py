"""The moments of an estimator's error, propagated exactly through a compiled plan.

A plan (see `architectures`) is a linear map of the data, so the joint first and second
moments of Z_k = [x_k; zeta_k] (true state, and the estimator state's deviation
zeta_k = s_k - D_k x_k) follow from the true model (F_t, GQG_t, H_t, R_t, initial distribution)
step by step:

    x_k = F_t x_{k-1} + w,   s_k = T_k s_{k-1} + U_k (H_t x_k + v_k),
    mu_k = A_k mu_{k-1},     C_k = A_k C_{k-1} A_k^T + B_v R B_v^T + B_w GQG B_w^T.

`exact` reads the error statistics off them; per-run maps (a leading run or node axis) give
per-run moments, the matrix products broadcasting over that axis.
"""

from __future__ import annotations

import numpy as np

from ..errors import NumericalError
from .architectures import Plan, StepMap
from .intervals import same_per_interval
from .linalg import mT, sym
from .model import System


def coupling(plan: Plan, truth: System) -> bool:
    """Whether the estimator state deviation zeta = s - D x depends on the true state x.

    For an estimator built on the true dynamics and measurement matrices (F and H; the noise
    covariances and the prior may differ), zeta_k = T zeta_{k-1} + (U H - D) w + U v exactly:
    the x terms cancel, so x, whose covariance grows without bound for a random walk, can be
    left out, avoiding a catastrophic cancellation. A different F or H keeps the x terms, however
    small the difference: its effect grows with x.
    """
    model = plan.system
    if model is None:
        return True
    same_F = np.array_equal(model.F, truth.F) and (
        model.Fs is truth.Fs
        or (
            model.Fs is not None
            and truth.Fs is not None
            and same_per_interval(model.Fs, model.F, truth.Fs, truth.F, len(model.Fs))
        )
    )
    return not (same_F and np.array_equal(model.linear_measurement(), truth.linear_measurement()))


def mv(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A x for x (d,) or (runs, d) and A (r, d) or (runs, r, d)."""
    return A @ x if x.ndim == 1 else (A @ x[..., None])[..., 0]


def rmul(X: np.ndarray, S: np.ndarray) -> np.ndarray:
    """X S for a matrix S shared by all runs: per-run X as one product of its stacked rows
    (numpy calls BLAS once per run otherwise, which for small matrices costs more than the
    arithmetic)."""
    if X.ndim == 2 or S.ndim > 2:
        return X @ S
    return (X.reshape(-1, X.shape[-1]) @ S).reshape(X.shape[:-1] + S.shape[-1:])


def congruences(terms: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """sum_i X_i S_i X_i^T, term by term in order (a product by a shared S through `rmul`)."""
    out = None
    for X, S in terms:
        term = rmul(X, S) @ mT(X)
        out = term if out is None else out + term
    return out


def hcat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[a, b] side by side, the run axis broadcast when one of them has it."""
    if a.ndim == b.ndim == 2:
        return np.hstack([a, b])
    batch = np.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    a = np.broadcast_to(a, batch + a.shape[-2:])
    return np.concatenate([a, np.broadcast_to(b, batch + b.shape[-2:])], axis=-1)


def initial_moments(plan: Plan, truth: System) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean and covariance of Z = [x_0; zeta_{-1}] before the first update (x_0 ~ the true
    initial distribution, zeta_{-1} = s0 - D0 x_0), and the size of the x block (0 when x
    decouples, see `coupling`)."""
    n = truth.n
    init = truth.truth_initial
    nx = n if coupling(plan, truth) else 0
    D0 = plan.D0
    Jx = np.vstack([np.eye(n), -D0])[n - nx :] if nx else -D0
    mu = np.concatenate([init.mean, plan.s0 - D0 @ init.mean])[n - nx :]
    return mu, Jx @ init.cov @ Jx.T, nx


def step_moments(
    st: StepMap,
    k: int,
    mu: np.ndarray,
    C: np.ndarray,
    D_prev: np.ndarray,
    truth: System,
    nx: int,
    Ht: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The moments of Z_k from those of Z_{k-1} through step k's map (dense maps; per-run or
    per-node maps and moments broadcast over their leading axis); Ht the truth's stacked H."""
    n = truth.n
    d_prev = mu.shape[-1] - nx
    d = st.T.shape[-2]
    batch = np.broadcast_shapes(st.T.shape[:-2], st.U.shape[:-2], mu.shape[:-1])
    F = truth.F_at(k) if k > 0 else np.eye(n)
    UHD = rmul(st.U, Ht) - st.D
    Bw = UHD
    if nx:
        A = np.zeros(batch + (nx + d, nx + d_prev))
        A[..., nx:, nx:] = st.T
        A[..., :nx, :nx] = F
        A[..., nx:, :nx] = st.T @ D_prev + UHD @ F
        Bw = np.concatenate([np.broadcast_to(np.eye(n), UHD.shape[:-2] + (n, n)), UHD], -2)
        Bv = np.zeros(batch + (nx + d, Ht.shape[0]))
        Bv[..., nx:, :] = st.U
    else:  # zeta alone: the maps themselves (contiguous, as a padded copy would be)
        A, Bv = np.ascontiguousarray(st.T), np.ascontiguousarray(st.U)
    noise = [(Bv, truth.R_at(k))] + ([(Bw, truth.GQG_at(k))] if k > 0 else [])
    return mv(A, mu), sym(congruences([(A, C), *noise]))


def forward_moments(plan: Plan, truth: System) -> tuple[list, list, int, int]:
    """Mean and covariance of Z_k = [x_k; zeta_k], zeta_k = s_k - D_k x_k, for every k.

    Returns the lists, the size of the x block (0 when x decouples, see `coupling`) and the
    step from which the moments and the plan's map repeat (K + 1 if they never settle): once
    the plan repeats its steady-state map and the moments stop changing, later steps repeat
    them too (the same objects in the lists). Per-run maps give per-run moments (runs, ...).
    """
    mu, C, nx = initial_moments(plan, truth)
    Ht = truth.linear_measurement()
    mus, Cs = [], []
    D_prev = plan.D0
    K1 = len(plan.steps)
    for k, st in enumerate(plan.steps):
        mu_new, C_new = step_moments(st, k, mu, C, D_prev, truth, nx, Ht)
        if (
            not nx
            and k > 1
            and st is plan.steps[k - 1]
            and np.abs(C_new - C).max() <= 1e-15 * np.abs(C_new).max()
            and np.abs(mu_new - mu).max() <= 1e-15 * max(np.abs(mu_new).max(), 1e-300)
        ):
            mus.extend([mu_new] * (K1 - k))
            Cs.extend([C_new] * (K1 - k))
            return mus, Cs, nx, k
        mu, C = mu_new, C_new
        mus.append(mu)
        Cs.append(C)
        D_prev = st.D
    # A non-finite entry stays non-finite (inf * 0 and inf - inf are NaN): the last step tells.
    if not (np.isfinite(C).all() and np.isfinite(mu).all()):
        k = next(
            k
            for k, (m, c) in enumerate(zip(mus, Cs, strict=True))
            if not np.isfinite(c).all() or not np.isfinite(m).all()
        )
        raise NumericalError(f"step {k}: the true error covariance overflows")
    return mus, Cs, nx, K1
