"""Static fusion rules for N estimates of the same state (Ajgl-Simandl-Dunik, Sec. II; Gustafsson-
Hendeby, "The Sensor Fusion Formula").

Each rule returns the weighting matrices c_i of eq. (2) (so a caller can apply one set of weights to
many runs at once) and the covariance the rule claims for the fused estimate; `fuse` applies
weights.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from .ci import Criterion, ci_omegas
from .linalg import inv_or_nan, mT, spd_inv, sym


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
    E = np.broadcast_to(E0 if E is None else E, batch + (N * n, n))
    # Scale every input and every state to unit size (Jacobi scaling): the KKT system of
    # J~ = D^-1 J D^-1 and E~ = D^-1 E S^-1 has the weights C = S^-1 C~ D^-1 with the same P up
    # to the weighting S^-1 P S^-1 of its trace, so the same optimum: the generalised Millman
    # estimate does not depend on the units of the states. One scale for the whole matrix would
    # let the rank cut-off below drop the variance of a state in small units (a turn rate
    # beside positions, millimetres beside kilometres) as if it were rounding.
    d = np.sqrt(np.abs(joint.diagonal(0, -2, -1)))  # (..., N n)
    d = np.where(d > 0, d, 1.0)
    Ed = E / d[..., :, None]
    e = np.abs(Ed).max(axis=-2)  # (..., n)
    e = np.where(e > 0, e, 1.0)
    kkt = np.zeros(batch + (N * n + n, N * n + n))
    kkt[..., : N * n, : N * n] = joint / (d[..., :, None] * d[..., None, :])
    kkt[..., : N * n, N * n :] = Ed / e[..., None, :]
    kkt[..., N * n :, : N * n] = mT(kkt[..., : N * n, N * n :])
    if kkt.ndim == 2:
        sol = np.linalg.lstsq(kkt, rhs, rcond=1e-12)[0]  # SVD-based minimum-norm solution
    else:  # lstsq does not batch; the pseudo-inverse gives the same minimum-norm solution
        sol = np.linalg.pinv(kkt, rcond=1e-12, hermitian=True) @ rhs
    # C^T = D^-1 C~^T S^-1: back to the inputs' and the states' units
    C = mT(sol[..., : N * n, :] / (d[..., :, None] * e[..., None, :]))
    if general:
        ok = np.max(np.abs(C @ E - np.eye(n)), axis=(-2, -1)) < 1e-8
        C = np.where(ok[..., None, None], C, np.nan)
    P = sym(C @ joint @ mT(C))
    return C, P


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
