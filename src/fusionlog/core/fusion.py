"""Static fusion rules for N estimates of the same state (Ajgl-Simandl-Dunik, Sec. II; Gustafsson-
Hendeby, "The Sensor Fusion Formula").

Each rule returns the weighting matrices c_i of eq. (2) (so a caller can apply one set of weights to
many runs at once) and the covariance the rule claims for the fused estimate; `fuse` applies
weights.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from typing import Literal

import numpy as np

from .linalg import inv_or_nan, is_invertible, mT, spd_inv, sym


def fuse(weights: Sequence[np.ndarray], estimates: Sequence[np.ndarray]) -> np.ndarray:
    """x = sum_i c_i x_i, eq. (2); estimates may carry leading run dimensions (..., n)."""
    return sum(np.einsum("...ij,...j->...i", c, x) for c, x in zip(weights, estimates, strict=True))


def millman_weights(covs: Sequence[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Millman's formula for independent estimates, eqs. (10)-(11) and (32)-(34).

    P = (sum_j P_jj^-1)^-1, c_i = P P_ii^-1.
    """
    return ci_weights(covs, np.ones(len(covs)))


def bar_shalom_campo(
    P11: np.ndarray, P22: np.ndarray, P12: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray]:
    """Bar-Shalom-Campo combination of two correlated estimates, eqs. (8)-(9)."""
    P21 = mT(P12)
    D = P11 + P22 - P12 - P21
    # c2 = (P11 - P12) D^-1, computed as a solve with D^T = D.
    c2 = mT(np.linalg.solve(D, mT(P11 - P12)))
    c1 = np.eye(P11.shape[-1]) - c2
    P = P11 - c2 @ (P11 - P21)
    return [c1, c2], sym(P)


def gmf_weights(
    joint: np.ndarray, n: int, E: np.ndarray | None = None
) -> tuple[list[np.ndarray], np.ndarray]:
    """Generalised Millman formula, eqs. (2)-(7), in constrained least-squares form.

    Minimises J of eq. (5), tr(C Sigma C^T), subject to sum_i c_i = I (eq. 7), where Sigma is the
    (N n x N n) joint error covariance with blocks P_ij of eq. (1). The stationarity conditions are
    the KKT system  [Sigma E; E^T 0] [C^T; L] = [0; I]  with E = [I; ...; I]. Eq. (6) is this system
    with the multiplier eliminated; it needs Sigma - blocks to be invertible, which fails in the
    paper's own example (identical local filters sharing the prior). The KKT system is solved by
    least squares (pseudo-inverse), whose minimum-norm solution is optimal even when Sigma is
    singular: weights that differ by a null direction of Sigma give the same estimate almost surely.

    `E` generalises the constraint to sum_i c_i E_i = I for inputs s_i = E_i x + noise (an
    information vector has E_i = Y_i); weights that cannot meet it (too little information in
    all inputs together) come back as NaN. Returns the weights c_i and P of eq. (4).
    """
    C, P = gmf_weight_matrix(joint, n, E)
    N = joint.shape[-1] // n
    return [C[..., :, i * n : (i + 1) * n] for i in range(N)], P


@lru_cache(maxsize=32)
def _kkt_constants(N: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """E = [I; ...; I] (N n x n) of eq. (7) and the KKT right-hand side [0; I]."""
    rhs = np.zeros((N * n + n, n))
    rhs[N * n :] = np.eye(n)
    E = np.tile(np.eye(n), (N, 1))
    E.flags.writeable = rhs.flags.writeable = False  # shared by every call
    return E, rhs


def gmf_weight_matrix(
    joint: np.ndarray, n: int, E: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """`gmf_weights` with the weights side by side, C = [c_1 ... c_N] (..., n, N n): what a
    caller applying them to the stacked estimates uses directly. Returns C and P of eq. (4)."""
    N = joint.shape[-1] // n
    batch = joint.shape[:-2]
    general = E is not None
    E0, rhs = _kkt_constants(N, n)
    # Scale so that the KKT matrix mixes blocks of comparable size (R may span 1e-8 .. 1e8).
    scale = np.abs(joint.diagonal(0, -2, -1)).max(axis=-1)[..., None, None]
    scale = np.where(scale > 0, scale, 1.0)
    if general:
        E = np.broadcast_to(E, batch + (N * n, n))
        e_scale = np.abs(E).max(axis=(-2, -1))[..., None, None]
        e_scale = np.where(e_scale > 0, e_scale, 1.0)
        Es = E / e_scale
    else:  # E = [I; ...; I] needs no scaling
        Es = E0
    kkt = np.zeros(batch + (N * n + n, N * n + n))
    kkt[..., : N * n, : N * n] = joint / scale
    kkt[..., : N * n, N * n :] = Es
    kkt[..., N * n :, : N * n] = mT(Es)
    if kkt.ndim == 2:
        sol = np.linalg.lstsq(kkt, rhs, rcond=1e-12)[0]  # SVD-based minimum-norm solution
    else:  # lstsq does not batch; the pseudo-inverse gives the same minimum-norm solution
        sol = np.linalg.pinv(kkt, rcond=1e-12, hermitian=True) @ rhs
    Ct = sol[..., : N * n, :]  # (N n, n): stacked c_i^T
    if general:
        Ct = Ct / e_scale  # back to the unscaled E
    C = mT(Ct)
    if general:
        ok = np.max(np.abs(C @ E - np.eye(n)), axis=(-2, -1)) < 1e-8
        C = np.where(ok[..., None, None], C, np.nan)
    P = sym(C @ joint @ mT(C))
    return C, P


Criterion = Literal["trace", "det"]


#: Problems solved together by one SLSQP call (the Jacobian it builds is dense in them).
CI_GROUP = 8


def _ci_costs(
    Ys: np.ndarray, omega: np.ndarray, criterion: Criterion, gradient: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Costs tr(P) or log det(P), P = (sum_i w_i Y_i)^-1, of B problems and their gradients
    (None with gradient=False).

    Ys (B, N, n, n) informations, omega (B, N). d tr(P)/d w_i = -tr(P Y_i P) and
    d log det(P)/d w_i = -tr(P Y_i). Both costs are convex in omega (tr X^-1 and -log det X are
    convex on positive definite X), so a local minimum on the simplex is the global one.
    """
    Y = np.einsum("bi,bijk->bjk", omega, Ys)
    sign, logdet = np.linalg.slogdet(Y)
    bad = sign <= 0
    Y[bad] = np.eye(Y.shape[-1])
    P = np.linalg.inv(Y)
    g = None
    if criterion == "trace":
        f = np.trace(P, axis1=-2, axis2=-1)
        if gradient:
            g = -np.einsum("bjk,bikl,blj->bi", P, Ys, P)
    else:
        f = -logdet
        if gradient:
            g = -np.einsum("bjk,bikj->bi", P, Ys)
    f = np.where(bad, np.inf, f)
    return f, g


def ci_omegas(infos: np.ndarray, criterion: Criterion = "trace") -> np.ndarray:
    """Covariance-intersection weights for B independent problems at once, (B, N) on the simplex.

    infos (B, N, n, n): the inputs' information matrices P_i^-1. When every input's information
    is invertible, every omega gives a finite cost and the problems are separable, so groups of
    them go to one SLSQP call (scipy) as a single problem with one simplex constraint per member:
    one optimiser call per group instead of one per time step. A problem with a singular input
    (a local filter that cannot see the whole state yet) has infinite cost on part of the simplex
    and is solved on its own; one whose inputs together are singular has no CI estimate (NaN).
    Each answer is compared with the end points (an input alone), which win only if better by
    more than rounding: with equal input covariances every omega gives the same P, the interior
    answer also averages the estimates, and letting rounding pick an end point would make the
    fused estimate jump from step to step.
    """
    Ys = np.asarray(infos, dtype=float)
    B, N = Ys.shape[:2]
    if N == 1:
        return np.ones((B, 1))
    # omega does not change when one problem's informations are scaled together; scaling each
    # to unit mean trace keeps SLSQP's stopping test (on the summed cost) fair to every member.
    tr = np.trace(Ys.mean(axis=1), axis1=-2, axis2=-1) / Ys.shape[-1]
    Ys = Ys / np.where(tr > 0, tr, 1.0)[:, None, None, None]
    out = np.full((B, N), np.nan)
    solvable = is_invertible(Ys.mean(axis=1))
    regular = np.flatnonzero(solvable & is_invertible(Ys).all(axis=1))
    for g0 in range(0, len(regular), CI_GROUP):
        idx = regular[g0 : g0 + CI_GROUP]
        out[idx] = _ci_group(Ys[idx], criterion)
    for i in np.flatnonzero(solvable & ~is_invertible(Ys).all(axis=1)):
        out[i] = _ci_group(Ys[i : i + 1], criterion)[0]
    return out


def _ci_group(Yg: np.ndarray, criterion: Criterion) -> np.ndarray:
    """SLSQP on b separable CI problems (b, N, n, n) at once, then the end-point check."""
    b, N = Yg.shape[:2]
    A = np.kron(np.eye(b), np.ones((1, N)))

    def fun(w: np.ndarray) -> tuple[float, np.ndarray]:
        f, grad = _ci_costs(Yg, w.reshape(b, N), criterion)
        return float(f.sum()), np.nan_to_num(grad.ravel(), posinf=0.0, neginf=0.0)

    from scipy import optimize  # here: its import costs ~0.2 s that only CI needs

    res = optimize.minimize(
        fun,
        np.full(b * N, 1.0 / N),
        jac=True,
        method="SLSQP",
        bounds=[(0.0, 1.0)] * (b * N),
        constraints=[{"type": "eq", "fun": lambda w: A @ w - 1.0, "jac": lambda w: A}],
        options={"ftol": 1e-15, "maxiter": 500},
    )
    w = np.clip(res.x.reshape(b, N), 0.0, 1.0)
    w[w < 1e-12] = 0.0  # SLSQP lands within rounding of an active bound
    w /= w.sum(axis=1, keepdims=True)
    # The answer and the N end points (e_i: input i alone) costed in one call, as N + 1 stacked
    # copies of the group; each problem's cost is computed on its own all the same.
    ends = np.broadcast_to(np.eye(N)[:, None, :], (N, b, N))
    cands = np.concatenate([w[None], ends]).reshape(-1, N)
    Yc = np.broadcast_to(Yg, (N + 1,) + Yg.shape).reshape((-1,) + Yg.shape[1:])
    costs = _ci_costs(Yc, cands, criterion, gradient=False)[0].reshape(N + 1, b)
    best, cost = w, costs[0]
    if not np.isfinite(cost).all():  # the optimiser stepped out: fall back to the start point
        bad = ~np.isfinite(cost)
        best[bad] = 1.0 / N
        cost = _ci_costs(Yg, best, criterion, gradient=False)[0]
    for i in range(N):
        c = costs[i + 1]
        better = c < cost - 1e-9 * np.abs(cost)
        best = np.where(better[:, None], ends[i], best)
        cost = np.where(better, c, cost)
    return best


def ci_omega(covs: Sequence[np.ndarray], criterion: Criterion = "trace") -> np.ndarray:
    """Weights omega of covariance intersection for one set of estimates (see `ci_omegas`)."""
    return ci_omegas(spd_inv(np.stack(covs))[None], criterion)[0]


def ci_weights(
    covs: Sequence[np.ndarray], omega: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray]:
    """Covariance intersection ("safe fusion"): P^-1 = sum w_i P_i^-1, c_i = w_i P P_i^-1;
    with w = 1 it is Millman's formula.

    For any cross-correlation between the inputs, P bounds the true error covariance.
    """
    infos = [spd_inv(P) for P in covs]
    P = inv_or_nan(sum(w * Y for w, Y in zip(omega, infos, strict=True)))
    return [w * (P @ Y) for w, Y in zip(omega, infos, strict=True)], P
