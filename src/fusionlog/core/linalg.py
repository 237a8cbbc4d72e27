"""Small batched linear-algebra helpers shared by the filters and the fusion rules.

Every function accepts arrays with optional leading batch dimensions (..., n, n), so the same
code serves the shared-gain path (no batch) and the per-run path (batch = runs).
"""

from __future__ import annotations

import numpy as np


def sym(A: np.ndarray) -> np.ndarray:
    """Symmetric part; applied after every covariance update so rounding cannot accumulate."""
    # The ndarray method, not np.swapaxes: plan building calls this thousands of times, and the
    # module function's dispatch costs more than the arithmetic on a 2 x 2 matrix.
    return 0.5 * (A + A.swapaxes(-1, -2))


def mT(A: np.ndarray) -> np.ndarray:
    """Transpose of the last two axes."""
    return A.swapaxes(-1, -2)


def spd_inv(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix via a solve, symmetrised.

    np.linalg.inv is LAPACK's gesv with the identity as right-hand side, i.e. the same solve,
    without building and broadcasting the identity first.
    """
    return sym(np.linalg.inv(A))


def is_invertible(Y: np.ndarray, rtol: float = 1e-13) -> np.ndarray:
    """Whether each symmetric PSD matrix has full rank (smallest eigenvalue above rtol * largest).

    Used to decide when an information-form filter that started without a prior has gathered
    enough information for a covariance to exist. A matrix with a NaN (e.g. the information of
    a fusion with no weights because nothing was observed yet) is not invertible.
    """
    finite = np.isfinite(Y).all(axis=(-2, -1))
    if not finite.all():  # LAPACK's eigensolver does not converge on NaN
        Y = np.where(finite[..., None, None], Y, 0.0)
    w = np.linalg.eigvalsh(Y)
    return finite & (w[..., 0] > rtol * np.maximum(w[..., -1], np.finfo(float).tiny))


def inv_or_nan(Y: np.ndarray, axes: tuple[int, ...] = ()) -> np.ndarray:
    """Covariance from an information matrix: Y^-1 where Y is invertible, NaN elsewhere (an
    estimate that does not exist yet, e.g. a filter started without a prior).

    When every matrix is invertible the inverse comes from a solve (`spd_inv`), otherwise the
    invertible ones from the pseudo-inverse. With `axes` (batch axes of Y, e.g. the local
    filters of a stack or the steps of a plan) that choice is made separately for each index
    along them, so the result equals calling this on each of those slices alone.
    """
    ok = is_invertible(Y)
    if np.all(ok):
        return spd_inv(Y)
    if not axes:
        Y = np.where(ok[..., None, None], Y, 0.0)  # the others are NaN anyway; no NaN in SVD
        return sym(np.where(ok[..., None, None], np.linalg.pinv(Y, hermitian=True), np.nan))
    # The slices along `axes` first, each one either wholly invertible or not.
    axes = tuple(a % ok.ndim for a in axes)  # batch axes: the same in Y and in ok
    front = tuple(range(len(axes)))
    Yf, okf = np.moveaxis(Y, axes, front), np.moveaxis(ok, axes, front)
    whole = okf.reshape(okf.shape[: len(axes)] + (-1,)).all(axis=-1)
    out = np.empty_like(Yf)
    out[whole] = spd_inv(Yf[whole])
    out[~whole] = inv_or_nan(Yf[~whole])  # not wholly invertible: each alone, pinv and NaN
    return np.moveaxis(out, front, axes)


def apply(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A v for v of shape (runs, d): one GEMM when A is shared, batched products when per run."""
    if A.ndim == 2:
        return v @ A.T
    return np.einsum("...ij,...j->...i", A, v)
