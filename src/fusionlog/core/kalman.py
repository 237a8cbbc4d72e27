"""Kalman filter steps, batched over leading dimensions (Ajgl-Simandl-Dunik, Sec. IV-A)."""

from __future__ import annotations

import numpy as np

from .linalg import mm, mT, solve, spd_inv, sym


def gain(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Kalman gain K = P H^T (H P H^T + R)^-1, eq. (17), solved with the innovation covariance
    (its pseudo-inverse where it is singular to working precision, see `linalg.solve`)."""
    HP = mm(H, P)
    S = sym(mm(HP, mT(H)) + R)
    return mT(solve(S, HP, hermitian=True, what="the innovation covariance H P H' + R"))


def joseph(
    P: np.ndarray, K: np.ndarray, H: np.ndarray, R: np.ndarray, A: np.ndarray | None = None
) -> np.ndarray:
    """Joseph form (I - K H) P (I - K H)^T + K R K^T of eq. (18): PSD by construction.

    A = I - K H may be passed by a caller that needs it anyway.
    """
    if A is None:
        A = np.eye(P.shape[-1]) - mm(K, H)
    return sym(mm(mm(A, P), mT(A)) + mm(mm(K, R), mT(K)))


def update_joseph(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Measurement update, eq. (14) with the Joseph-form covariance."""
    K = gain(P, H, R)
    innov = z - np.einsum("...ij,...j->...i", H, x)
    return x + np.einsum("...ij,...j->...i", K, innov), joseph(P, K, H, R)


def update_millman(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Measurement update as Millman fusion of the prediction and the ML estimate, eqs. (19)-(24).

    The ML estimate enters through its information P_ML^-1 = H^T R^-1 H and P_ML^-1 x_ML =
    H^T R^-1 z, so H^T R^-1 H need not be invertible (a position-only sensor of a 2-D state).
    """
    Rinv_H = np.linalg.solve(R, H)
    info_pred = spd_inv(P)
    P_post = spd_inv(info_pred + mT(H) @ Rinv_H)
    y = np.einsum("...ij,...j->...i", info_pred, x) + np.einsum("...ji,...j->...i", Rinv_H, z)
    return np.einsum("...ij,...j->...i", P_post, y), P_post
