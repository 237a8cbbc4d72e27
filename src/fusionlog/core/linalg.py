"""Small batched linear-algebra helpers shared by the filters and the fusion rules.

Every function accepts arrays with optional leading batch dimensions (..., n, n), so the same
code serves the shared-gain path (no batch) and the per-run path (batch = runs).
"""

from __future__ import annotations

import numpy as np

from ..errors import NumericalError


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


def solve(A: np.ndarray, B: np.ndarray, *, hermitian: bool = False) -> np.ndarray:
    """A^-1 B (batched) by LU; where A is singular to working precision, the minimum-norm
    least-squares solution A^+ B (`hermitian`: A is symmetric, e.g. a covariance).

    A singular A is a tolerance question, not an error: the innovation covariance
    H P H' + R of identical sensors with tiny noise (R = 1e-16 against P = 0.05) is
    p 1 1' + r I, whose small eigenvalues drown in the rounding of the large one. The
    pseudo-inverse drops exactly those directions, which is the limit of the exact solution
    (for a gain, P H' S^+ is the gain of the noise-free limit). Only singular systems take the
    slower route, so regular ones keep LU's numbers to the last bit.
    """
    try:
        return np.linalg.solve(A, B)
    except np.linalg.LinAlgError:
        require_finite(A, "a matrix to be solved with")
        return np.linalg.pinv(A, hermitian=hermitian) @ B


def require_finite(A: np.ndarray, what: str) -> None:
    """Raise NumericalError ("<what> overflows ...") unless every entry of A is finite.

    Checked where a recursion produces a new covariance, so that an overflow is reported at
    the step where it happens, and never handed to LAPACK, which answers non-finite input
    with convergence failures (and prints to the terminal).
    """
    if not np.isfinite(A).all():
        raise NumericalError(
            f"{what} overflows (entries beyond the float range, about 1.8e308, or inf - inf)"
        )


def bc(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """np.broadcast_to, skipped when nothing is to be done (it costs microseconds per call, and
    plan building calls it a dozen times a step)."""
    return a if a.shape == shape else np.broadcast_to(a, shape)


def block_diag(mats: list[np.ndarray]) -> np.ndarray:
    """Block-diagonal matrix of matrices with broadcastable batch dimensions."""
    batch = np.broadcast_shapes(*(m.shape[:-2] for m in mats))
    rows = sum(m.shape[-2] for m in mats)
    cols = sum(m.shape[-1] for m in mats)
    out = np.zeros(batch + (rows, cols))
    r = c = 0
    for m in mats:
        out[..., r : r + m.shape[-2], c : c + m.shape[-1]] = m
        r, c = r + m.shape[-2], c + m.shape[-1]
    return out


def stack_diag(X: np.ndarray) -> np.ndarray:
    """Block-diagonal matrix of a stack: (..., S, a, b) -> (..., S a, S b)."""
    *lead, S, a, b = X.shape
    out = np.zeros((*lead, S, a, S, b))
    i = np.arange(S)
    out[..., i, :, i, :] = np.moveaxis(X, -3, 0) if lead else X  # the index puts S first
    return out.reshape((*lead, S * a, S * b))


def stack_rows(X: np.ndarray) -> np.ndarray:
    """A stack's matrices one above the other: (..., S, a, b) -> (..., S a, b)."""
    *lead, S, a, b = X.shape
    return X.reshape((*lead, S * a, b))


def stack_cols(X: np.ndarray) -> np.ndarray:
    """A stack's matrices side by side: (..., S, a, b) -> (..., a, S b)."""
    *lead, S, a, b = X.shape
    return X.swapaxes(-3, -2).reshape((*lead, a, S * b))


def sum_after(a: np.ndarray, X: np.ndarray) -> np.ndarray:
    """a + X_1 + ... + X_S for a stack X (..., S, p, q), added in that order (a numpy sum over
    a leading axis adds sequentially), as a sum over the sensors written out would."""
    return np.concatenate([a[..., None, :, :], X], axis=-3).sum(axis=-3)
