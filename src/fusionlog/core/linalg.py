"""Small batched linear-algebra helpers shared by the filters and the fusion rules.

Every function accepts arrays with optional leading batch dimensions (..., n, n), so the same
code serves the shared-gain path (no batch) and the per-run path (batch = runs).

Large batches of small matrices (the per-run path: 10^4 runs of 2 x 2 covariances) do not go
through numpy's stacked routines, which cost about a microsecond per matrix (np.matmul,
np.linalg.solve, inv, eigvalsh loop over the matrices), but through the *batch kernels* of
`core.kernels`: the same products, Cholesky and LU factorisations written entry by entry,
each entry one elementwise numpy operation over the whole batch. They work on the batch-last
("lanes") memory layout: an array still has the shape batch + (p, q), but its memory is
(p, q) + batch, so that every entry A[..., i, j] is one contiguous vector over the runs. The
kernels return arrays in that layout and numpy's elementwise operations keep it, so a builder
written with `mm`, `solve`, `spd_inv` and `sym` runs on lanes from step to step. Small batches
(below `KERNEL_MIN_BATCH`, e.g. the shared path's stack of a few local filters) keep numpy's
routines and their numbers to the last bit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial, wraps
from typing import Any

import numpy as np

from ..errors import NumericalError
from .kernels import (  # noqa: F401 - the batch kernels, used here and re-exported
    KERNEL_MAX_DIM,
    KERNEL_MIN_BATCH,
    PIVOT_RTOL,
    all_finite,
    apply_shared,
    buffer,
    cholesky,
    cholesky_inverse,
    cholesky_solve,
    kernels_for,
    lanes,
    lanes_copy,
    lanes_empty,
    lanes_of,
    many_matrices,
    mm,
    mv,
    require_finite,
    solve_kernel,
    solve_lapack,
    solve_spd_or_flag,
    spd_inv_kernel,
    stack_matrices,
    stack_rows,
    take_runs,
    unlanes,
)


def sym(A: np.ndarray) -> np.ndarray:
    """Symmetric part; applied after every covariance update so rounding cannot accumulate."""
    # The ndarray method, not np.swapaxes: plan building calls this thousands of times, and the
    # module function's dispatch costs more than the arithmetic on a 2 x 2 matrix.
    return 0.5 * (A + A.swapaxes(-1, -2))


def mT(A: np.ndarray) -> np.ndarray:
    """Transpose of the last two axes."""
    return A.swapaxes(-1, -2)


def spd_inv(A: np.ndarray, what: str = "a covariance or information matrix") -> np.ndarray:
    """Inverse of a symmetric positive definite matrix via a solve, symmetrised.

    np.linalg.inv is LAPACK's gesv with the identity as right-hand side, i.e. the same solve,
    without building and broadcasting the identity first. A matrix singular to working
    precision raises NumericalError naming it (`what`). A large batch goes through the
    Cholesky kernel (exactly symmetric inverses).
    """
    if kernels_for(A):
        return spd_inv_kernel(A, lambda a: _spd_inv_lapack(a, what))[0]
    return _spd_inv_lapack(A, what)


def _spd_inv_lapack(A: np.ndarray, what: str) -> np.ndarray:
    try:
        return sym(np.linalg.inv(A))
    except np.linalg.LinAlgError:
        raise NumericalError(f"{what} is singular to working precision") from None


def wide_diagonal(A: np.ndarray, spread: float = 1e8) -> bool:
    """Whether some matrix of the batch has a positive diagonal spanning more than `spread`:
    badly scaled, where LU inverses lose the small entries (see `spd_inv_scaled`)."""
    d = A.diagonal(0, -2, -1)
    lo, hi = d.min(axis=-1), d.max(axis=-1)
    return bool(((lo > 0) & (hi > spread * lo)).any())


def spd_inv_scaled(
    A: np.ndarray, spread: float = 1e8, what: str = "a covariance or information matrix"
) -> np.ndarray:
    """`spd_inv`, through the Jacobi scaling D^-1/2 A D^-1/2 (D = diag A) for the matrices
    whose diagonal spans more than `spread`: A^-1 = D^-1/2 (D^-1/2 A D^-1/2)^-1 D^-1/2.

    LU on a covariance such as [[1e-300, 1e-300], [1e-300, 0.05]] (a position measured with
    R = 1e-300) returns an inverse whose off-diagonal entries are not even close to symmetric;
    the scaled matrix is well conditioned and inverts to full accuracy. Matrices of comparable
    diagonal take `spd_inv` (the same numbers to the last bit), after a test that costs about
    a microsecond on the few matrices of a step.

    A large batch goes through the Cholesky kernel without the scaling: Cholesky's accuracy
    does not depend on the scaling of the matrix (van der Sluis), only LU's does.
    """
    if kernels_for(A):
        return spd_inv_kernel(A, lambda a: _spd_inv_scaled_lapack(a, spread, what))[0]
    return _spd_inv_scaled_lapack(A, spread, what)


def _spd_inv_scaled_lapack(A: np.ndarray, spread: float, what: str) -> np.ndarray:
    d = A.diagonal(0, -2, -1)
    if d.size == 0:  # no matrices
        return np.empty(A.shape)
    if d.size <= 64:  # a few matrices: Python compares faster than numpy reduces
        dl = d.ravel().tolist()
        lo, hi = min(dl), max(dl)
    else:
        lo, hi = float(d.min()), float(d.max())
    if lo > 0 and hi <= spread * lo:  # none of them is wide
        return spd_inv(A, what)
    lo, hi = d.min(axis=-1), d.max(axis=-1)
    wide = (lo > 0) & (hi > spread * lo)
    if not wide.any():
        return spd_inv(A, what)
    s = 1.0 / np.sqrt(np.where(wide[..., None], d, 1.0))
    S = s[..., :, None] * s[..., None, :]
    scaled = spd_inv(A * S, what) * S
    if wide.all():
        return scaled
    wide = wide[..., None, None]
    return np.where(wide, scaled, spd_inv(np.where(wide, np.eye(A.shape[-1]), A), what))


#: In `definite`: eigenvalues of the Jacobi-scaled matrix within DEF_RTOL * n * max|eig| of zero
#: count as zero (its diagonal is 1, so this is about n * 1e-12 whatever the units).
DEF_RTOL = 1e-12


def definite(A: np.ndarray, *, strict: bool, rtol: float = DEF_RTOL) -> bool:
    """Whether the symmetric matrix A is positive definite (`strict`) or semidefinite to working
    precision: the one decision for every covariance a definition gives (R, Q, a prior's and a
    truth's covariance, cross-covariances) and for the bound's initial covariance.

    Decided on the Jacobi scaling C = D^-1/2 A D^-1/2 (D = diag A), a correlation matrix, so
    that it does not depend on the units of the states or measurements: a radar's
    R = diag(9e6 m^2, 1e-6 rad^2) is C = I, while its eigenvalues relative to the largest
    (1e-13) mix m^2 with rad^2. Cholesky's success depends on C in the same way (van der
    Sluis). A zero variance is allowed (semidefinite) only with a zero row: a nonzero
    covariance beside it makes a 2 x 2 minor negative, in any units.
    """
    A = 0.5 * A + 0.5 * A.T  # not (A + A^T) / 2: entries near 1e308 would overflow
    n = A.shape[0]
    d = np.diagonal(A)
    if (d < 0).any() or (strict and not (d > 0).all()):
        return False
    keep = d > 0
    if not keep.all():
        if (A[~keep] != 0).any():
            return False
        A, d = A[np.ix_(keep, keep)], d[keep]
        if not d.size:  # all zero: semidefinite
            return True
    s = np.sqrt(d)
    with np.errstate(over="ignore"):  # |C_ij| far above 1 (overflowing): indefinite anyway
        C = A / s[:, None] / s[None, :]
    if not np.isfinite(C).all():
        return False
    np.fill_diagonal(C, 1.0)  # d_i / s_i / s_i up to rounding
    w = np.linalg.eigvalsh(C)
    tol = rtol * n * float(np.max(np.abs(w)))
    return bool(w[0] > tol) if strict else bool(w[0] >= -tol)


def is_invertible(Y: np.ndarray, rtol: float = 1e-13) -> np.ndarray:
    """Whether each symmetric PSD matrix has full rank: its smallest eigenvalue above rtol times
    its largest, or that of its Jacobi scaling D^-1/2 Y D^-1/2 (D = diag Y) is.

    Used to decide when an information-form filter that started without a prior has gathered
    enough information for a covariance to exist. The scaled test accepts information that is
    badly scaled but regular, e.g. 3e16 on a position measured with R = 1e-16 beside 6 on a
    velocity, which the plain test would call singular forever; an unobserved direction keeps
    a zero diagonal (or a scaled eigenvalue at rounding level) and stays singular. A matrix
    with a NaN (e.g. the information of a fusion with no weights because nothing was observed
    yet) is not invertible.

    A large batch is first tested through its Cholesky inverse X: lambda_max <= tr Y and
    lambda_min >= 1 / ||X||_F, so tr Y ||X||_F < 0.1 / rtol proves the test above (with a
    margin for rounding); only the matrices it does not settle get the eigenvalues.
    """
    if kernels_for(Y):
        return _inverse_if_invertible(Y, rtol)[1]
    return _is_invertible_lapack(Y, rtol)


#: How far below zero the smallest eigenvalue of a reported covariance's correlation matrix
#: may lie (`not_a_covariance`): rounding moves it by about n eps times the conditioning of
#: the computation that made P; 1e-8 leaves that room and still refuses any real indefiniteness.
SEMIDEFINITE_TOL = 1e-8


def not_a_covariance(P: np.ndarray, semidefinite: bool = True) -> np.ndarray:
    """(...,) which of a batch of reported covariances (..., n, n) cannot be one: a negative
    variance, or (with `semidefinite`) a correlation matrix C = D^-1/2 P D^-1/2 (D = diag P, 1
    where it is zero, so the test does not depend on the units: m^2 beside rad^2) whose smallest
    eigenvalue is below -SEMIDEFINITE_TOL, i.e. P is not positive semidefinite. A matrix with a
    NaN or an infinity passes here: what an undefined estimate may be is the caller's rule."""
    bad = (np.diagonal(P, axis1=-2, axis2=-1) < 0).any(axis=-1)
    if not semidefinite:
        return bad
    n = P.shape[-1]
    flat, bad = P.reshape(-1, n, n), bad.reshape(-1)
    todo = np.flatnonzero(~bad & np.isfinite(flat).all(axis=(-2, -1)))
    if len(todo):
        Q = flat[todo]
        d = np.diagonal(Q, axis1=-2, axis2=-1)
        s = np.sqrt(np.where(d > 0, d, 1.0))
        with np.errstate(over="ignore", invalid="ignore"):  # beyond +-1 by far: refused below
            C = Q / s[:, :, None] / s[:, None, :]
        finite = np.isfinite(C).all(axis=(-2, -1))
        unsure = finite.copy()
        if kernels_for(C):  # C + tol I factors: lambda_min(C) > -tol, no eigenvalues needed
            with np.errstate(invalid="ignore", divide="ignore"):  # the others: eigenvalues
                _, ok = cholesky(lanes(lanes_copy(C + SEMIDEFINITE_TOL * np.eye(n))))
            unsure &= ~ok
        low = np.where(finite, 0.0, -np.inf)  # a correlation beyond +-1 by far: refused
        low[unsure] = np.linalg.eigvalsh(sym(C[unsure]))[:, 0]
        bad[todo] = low < -SEMIDEFINITE_TOL
    return bad.reshape(P.shape[:-2])


def _inverse_if_invertible(Y: np.ndarray, rtol: float = 1e-13) -> tuple[np.ndarray, np.ndarray]:
    """For a large batch: the Cholesky inverses (NaN where a matrix is not invertible) and
    `is_invertible`; the matrices the bound does not settle by the reference routines."""
    with np.errstate(all="ignore"):
        Yl = lanes(Y)
        L, ok = cholesky(Yl)
        X = cholesky_inverse(L)
        n = Yl.shape[0]
        tr = Yl[0, 0] if n == 1 else sum(Yl[i, i] for i in range(n))
        fro2 = (X * X).sum(axis=(0, 1))
        ok &= fro2 * (10.0 * rtol * tr) ** 2 < 1.0  # False where anything is not finite
    out = unlanes(X)
    undecided = ~ok
    if undecided.any():
        idx = np.nonzero(undecided)
        sub = Y[idx]
        good = _is_invertible_lapack(sub, rtol)
        ok[idx] = good
        out[idx] = _inv_or_nan_lapack(sub, good)
    return out, ok


def _is_invertible_lapack(Y: np.ndarray, rtol: float) -> np.ndarray:
    finite = np.isfinite(Y).all(axis=(-2, -1))
    if not finite.all():  # LAPACK's eigensolver does not converge on NaN
        Y = np.where(finite[..., None, None], Y, 0.0)
    w = np.linalg.eigvalsh(Y)
    ok = finite & (w[..., 0] > rtol * np.maximum(w[..., -1], np.finfo(float).tiny))
    if ok.all():
        return ok
    d = Y.diagonal(0, -2, -1)
    scalable = finite & (d > 0).all(axis=-1)
    s = 1.0 / np.sqrt(np.where(scalable[..., None], d, 1.0))
    Ys = np.where(scalable[..., None, None], Y * s[..., :, None] * s[..., None, :], 0.0)
    ws = np.linalg.eigvalsh(Ys)
    return ok | (scalable & (ws[..., 0] > rtol * ws[..., -1]))


def inv_or_nan(Y: np.ndarray) -> np.ndarray:
    """Covariance from an information matrix: Y^-1 where Y is invertible, NaN elsewhere (an
    estimate that does not exist yet, e.g. a filter started without a prior).

    Each matrix is inverted on its own (`spd_inv_scaled`, the others replaced by I for the
    batched call), so a result does not depend on the other matrices of the batch.
    """
    if kernels_for(Y):
        return _inverse_if_invertible(Y)[0]
    return _inv_or_nan_lapack(Y, is_invertible(Y))


def _inv_or_nan_lapack(Y: np.ndarray, ok: np.ndarray) -> np.ndarray:
    inv = partial(_spd_inv_scaled_lapack, spread=1e8, what="a covariance or information matrix")
    if np.all(ok):
        return inv(Y)
    ok = ok[..., None, None]
    return np.where(ok, inv(np.where(ok, Y, np.eye(Y.shape[-1]))), np.nan)


def apply(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A v for v of shape (runs, d): one GEMM when A is shared, batched products when per run."""
    if A.ndim == 2:
        return v @ A.T
    return np.einsum("...ij,...j->...i", A, v)


def solve(
    A: np.ndarray, B: np.ndarray, *, hermitian: bool = False, what: str = "a matrix to solve with"
) -> np.ndarray:
    """A^-1 B (batched) by LU; where A is singular to working precision, the minimum-norm
    least-squares solution A^+ B (`hermitian`: A is symmetric, e.g. a covariance).

    A singular A is a tolerance question, not an error: the innovation covariance
    H P H' + R of identical sensors with tiny noise (R = 1e-16 against P = 0.05) is
    p 1 1' + r I, whose small eigenvalues drown in the rounding of the large one. The
    pseudo-inverse drops exactly those directions, which is the limit of the exact solution
    (for a gain, P H' S^+ is the gain of the noise-free limit). Only singular systems take the
    slower route, so regular ones keep LU's numbers to the last bit. `what` names A in the
    NumericalError raised when A is not finite.

    A large batch goes through the kernels: Cholesky (`hermitian`) or LU with partial
    pivoting; the matrices with a pivot that small are solved as above, each on its own.
    """
    if kernels_for(A, B):
        return solve_kernel(A, B, hermitian, what)
    return solve_lapack(A, B, hermitian, what)


#: What numpy and Python raise when numbers cannot be computed with.
NUMERICAL_FAILURES = (np.linalg.LinAlgError, FloatingPointError, OverflowError, ZeroDivisionError)


@contextmanager
def numerical_errors(where: Callable[[], str]) -> Iterator[None]:
    """Run a computation without numpy's overflow warnings (overflows are checked explicitly,
    `require_finite`) and turn its numerical failures into one NumericalError prefixed by
    `where()` (called only on failure: it names the architecture and the step; a message
    that names the step itself, "step k: ...", follows it after a comma)."""
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            yield
    except NumericalError as e:
        sep = ", " if str(e).startswith("step ") else ": "
        raise NumericalError(f"{where()}{sep}{e}") from None
    except NUMERICAL_FAILURES as e:
        raise NumericalError(
            f"{where()}: a matrix is singular or overflows to working precision "
            f"({type(e).__name__}: {e})"
        ) from e


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
    if many_matrices(lead):  # lanes in, lanes out
        out = buffer((S * a, S * b), tuple(lead), zeros=True)
        Xl = lanes(X)
        for j in range(S):
            out[j * a : (j + 1) * a, j * b : (j + 1) * b] = Xl[..., j]
        return unlanes(out)
    if not lead:  # a few slice copies beat one fancy-indexed assignment (every plan step)
        out = np.zeros((S * a, S * b))
        for j in range(S):
            out[j * a : (j + 1) * a, j * b : (j + 1) * b] = X[j]
        return out
    out = np.zeros((*lead, S, a, S, b))
    i = np.arange(S)
    out[..., i, :, i, :] = np.moveaxis(X, -3, 0)  # the index puts S first
    return out.reshape((*lead, S * a, S * b))


def stack_cols(X: np.ndarray) -> np.ndarray:
    """A stack's matrices side by side: (..., S, a, b) -> (..., a, S b)."""
    *lead, S, a, b = X.shape
    if many_matrices(lead):
        out = buffer((a, S * b), tuple(lead))
        Xl = lanes(X)
        for j in range(S):
            out[:, j * b : (j + 1) * b] = Xl[..., j]
        return unlanes(out)
    return X.swapaxes(-3, -2).reshape((*lead, a, S * b))


def sum_after(a: np.ndarray, X: np.ndarray) -> np.ndarray:
    """a + X_1 + ... + X_S for a stack X (..., S, p, q), added in that order (a numpy sum over
    a leading axis adds sequentially), as a sum over the sensors written out would. A large
    batch is added up term by term in that order (the same numbers), keeping its layout."""
    if kernels_for(X):
        out = a + X[..., 0, :, :]
        for j in range(1, X.shape[-3]):
            out += X[..., j, :, :]
        return out
    return np.concatenate([a[..., None, :, :], X], axis=-3).sum(axis=-3)


def overflow_is_inf(f: Callable[..., Any]) -> Callable[..., Any]:
    """`f` with numpy's overflow and invalid-value warnings off, for code whose inf and NaN are
    the answer (metrics of a diverging model, entries near 1e308) and are reported as
    non-finite by the caller; a fresh error state per call."""

    @wraps(f)
    def quiet(*args: Any, **kwargs: Any) -> Any:
        with np.errstate(over="ignore", invalid="ignore"):
            return f(*args, **kwargs)

    return quiet


def finite_mean(a: np.ndarray) -> float | None:
    """The mean of the finite entries of `a` (None: there are none)."""
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else None
