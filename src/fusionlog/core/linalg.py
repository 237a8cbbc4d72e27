"""Small batched linear-algebra helpers shared by the filters and the fusion rules.

Every function accepts arrays with optional leading batch dimensions (..., n, n), so the same
code serves the shared-gain path (no batch) and the per-run path (batch = runs).
"""

from __future__ import annotations

import numpy as np


def sym(A: np.ndarray) -> np.ndarray:
    """Symmetric part; applied after every covariance update so rounding cannot accumulate."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def mT(A: np.ndarray) -> np.ndarray:
    """Transpose of the last two axes."""
    return np.swapaxes(A, -1, -2)


def spd_inv(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix via a solve, symmetrised."""
    eye = np.broadcast_to(np.eye(A.shape[-1]), A.shape)
    return sym(np.linalg.solve(A, eye))


def is_invertible(Y: np.ndarray, rtol: float = 1e-13) -> np.ndarray:
    """Whether each symmetric PSD matrix has full rank (smallest eigenvalue above rtol * largest).

    Used to decide when an information-form filter that started without a prior has gathered
    enough information for a covariance to exist.
    """
    w = np.linalg.eigvalsh(Y)
    return w[..., 0] > rtol * np.maximum(w[..., -1], np.finfo(float).tiny)


def inv_or_nan(Y: np.ndarray) -> np.ndarray:
    """Covariance from an information matrix: Y^-1 where Y is invertible, NaN elsewhere (an
    estimate that does not exist yet, e.g. a filter started without a prior)."""
    ok = is_invertible(Y)
    if np.all(ok):
        return spd_inv(Y)
    return sym(np.where(ok[..., None, None], np.linalg.pinv(Y, hermitian=True), np.nan))


def apply(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A v for v of shape (runs, d): one GEMM when A is shared, batched products when per run."""
    if A.ndim == 2:
        return v @ A.T
    return np.einsum("...ij,...j->...i", A, v)
