"""The batch kernels: products, Cholesky and LU factorisations of many small matrices at once.

numpy's stacked routines (np.matmul, np.linalg.solve, inv, eigvalsh) loop over the matrices at
about a microsecond each; here the same products and factorisations are written entry by entry,
each entry one elementwise numpy operation over the whole batch, on the batch-last ("lanes")
memory layout: an array keeps the shape batch + (p, q), but its memory is (p, q) + batch, so
that every entry A[..., i, j] is one contiguous vector over the runs. `fusionlog.core.linalg`
sends large batches of small matrices here and keeps numpy's routines (and their numbers to the
last bit) for the rest; a matrix a kernel cannot factor safely goes to LAPACK on its own.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..errors import NumericalError


def all_finite(A: np.ndarray) -> bool:
    """Whether every entry of A is finite. Small arrays (a step's covariance, checked at every
    step of plan building) are summed in Python, several times cheaper than np.isfinite on a
    2 x 2 matrix; a sum beyond the float range (entries near 1e308) counts as not finite,
    which is where the next product would overflow anyway."""
    if A.size <= 16:
        return math.isfinite(sum(A.ravel().tolist()))
    return bool(np.isfinite(A).all())


def require_finite(A: np.ndarray, what: str, *, per_step: bool = False) -> None:
    """Raise NumericalError ("<what> overflows ...") unless every entry of A is finite; with
    `per_step`, A's first axis runs over the steps and the message names the first bad one.

    Checked where a recursion produces a new covariance, so that an overflow is reported at
    the step where it happens, and never handed to LAPACK, which answers non-finite input
    with convergence failures (and prints to the terminal).
    """
    if all_finite(A):
        return
    where = ""
    if per_step:
        bad = ~np.isfinite(A).reshape(len(A), -1).all(axis=1)
        where = f"step {int(np.argmax(bad))}: "
    raise NumericalError(
        f"{where}{what} overflows (entries beyond the float range, about 1.8e308, or inf - inf)"
    )


def solve_lapack(A: np.ndarray, B: np.ndarray, hermitian: bool, what: str) -> np.ndarray:
    try:
        return np.linalg.solve(A, B)
    except np.linalg.LinAlgError:
        require_finite(A, what)
        return np.linalg.pinv(A, hermitian=hermitian) @ B


def many_matrices(batch: list[int] | tuple[int, ...]) -> bool:
    """Whether a batch shape holds enough matrices for the lanes layout (see `kernels_for`)."""
    return bool(batch) and math.prod(batch) >= KERNEL_MIN_BATCH


def stack_rows(X: np.ndarray) -> np.ndarray:
    """A stack's matrices one above the other: (..., S, a, b) -> (..., S a, b)."""
    *lead, S, a, b = X.shape
    if many_matrices(lead):
        try:  # lanes of a stack (see `buffer`): a reshape, no copy
            view = X.view()
            view.shape = (*lead, S * a, b)
            return view
        except AttributeError:
            out = buffer((S * a, b), tuple(lead))
            Xl = lanes(X)
            for j in range(S):
                out[j * a : (j + 1) * a] = Xl[..., j]
            return unlanes(out)
    return X.reshape((*lead, S * a, b))


# ---------------------------------------------------------------------------------------------
# Batch kernels: large batches of small matrices, one elementwise numpy operation per entry.
#
# A 2 x 2 product of 10^4 runs is 1.4 ms as np.matmul (~1 us a matrix) and ~0.07 ms as eight
# multiplications and four additions over the runs. The kernels take and return the usual shape
# batch + (p, q) in the lanes layout (module docstring; any layout works). A matrix they cannot
# factor safely (a pivot below PIVOT_RTOL of its scale, a non-finite entry) is recomputed alone
# by the shared path's LAPACK routine: a (nearly) singular matrix gets exactly its treatment.

#: Batches of at least this many matrices go through the kernels (tests lower it to send small
#: batches through them as well).
KERNEL_MIN_BATCH = 64
#: Matrices with a side above this keep numpy's routines (a kernel makes ~n^3 numpy calls).
KERNEL_MAX_DIM = 8
#: A Cholesky pivot below PIVOT_RTOL times its diagonal entry, or an LU pivot below PIVOT_RTOL
#: times the largest entry of its matrix, sends that matrix to LAPACK.
PIVOT_RTOL = 1e-8

_TINY = np.finfo(float).tiny
_LANES: dict[int, tuple[int, ...]] = {}
_UNLANES: dict[int, tuple[int, ...]] = {}


def lanes(A: np.ndarray) -> np.ndarray:
    """The (p, q) + batch view of a batch + (p, q) array: lanes(A)[i, j] is A[..., i, j]."""
    nd = A.ndim
    ax = _LANES.get(nd)
    if ax is None:
        ax = _LANES[nd] = (nd - 2, nd - 1, *range(nd - 2))
    return A.transpose(ax)


def unlanes(X: np.ndarray) -> np.ndarray:
    """The batch + (p, q) view of a (p, q) + batch array (the inverse of `lanes`)."""
    nd = X.ndim
    ax = _UNLANES.get(nd)
    if ax is None:
        ax = _UNLANES[nd] = (*range(2, nd), 0, 1)
    return X.transpose(ax)


def buffer(
    lead: tuple[int, ...], batch: tuple[int, ...], zeros: bool = False, dtype: type = float
) -> np.ndarray:
    """An uninitialised (or zero) array of shape lead + batch in the lanes memory order: the
    largest batch axis (the runs) is the contiguous one, the lead (matrix) axes come before it
    and the other batch axes (a stack of local filters, the steps) before those. So a stack of
    S matrices of each run is, in memory, S matrices of lanes one after the other: stacking
    them into one tall matrix (`stack_rows`) is a reshape."""
    nl, nb = len(lead), len(batch)
    if nb < 2:
        return (np.zeros if zeros else np.empty)(lead + batch, dtype=dtype)
    inner = max(range(nb), key=lambda i: batch[i])  # the first of the largest
    outer = [i for i in range(nb - 1, -1, -1) if i != inner]
    shape = (*(batch[i] for i in outer), *lead, batch[inner])
    mem = (np.zeros if zeros else np.empty)(shape, dtype=dtype)
    # memory axes: the outer batch axes, the lead axes, the inner batch axis
    where = {b: j for j, b in enumerate(outer)}
    where[inner] = len(outer) + nl
    return mem.transpose((*range(len(outer), len(outer) + nl), *(where[i] for i in range(nb))))


def take_runs(A: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """A[idx] along the first (runs) axis; a large result in the lanes layout."""
    if not many_matrices((len(idx),)):
        return A[idx]
    return np.moveaxis(np.take(np.moveaxis(A, 0, -1), idx, axis=-1), -1, 0)


def stack_matrices(arrays: list[np.ndarray]) -> np.ndarray:
    """np.stack(arrays) of matrices batch + (p, q); a large batch in the lanes memory order
    (the new, step, axis is not the contiguous one)."""
    first = arrays[0]
    if not kernels_for(first):
        return np.stack(arrays)
    *batch, p, q = first.shape
    out = buffer((p, q), (len(arrays), *batch))  # (p, q, L) + batch
    for j, a in enumerate(arrays):
        out[:, :, j] = lanes(a)
    return unlanes(out)


def _all_true(batch: tuple[int, ...]) -> np.ndarray:
    ok = buffer((), batch, dtype=bool)
    ok.fill(True)
    return ok


def lanes_empty(batch: tuple[int, ...], p: int, q: int) -> np.ndarray:
    """An uninitialised batch + (p, q) array in the lanes layout."""
    return unlanes(buffer((p, q), batch))


def lanes_copy(A: np.ndarray) -> np.ndarray:
    """A copy of A (broadcast or not) in the lanes layout."""
    X = lanes_empty(A.shape[:-2], *A.shape[-2:])
    X[...] = A
    return X


def kernels_for(*arrays: np.ndarray) -> bool:
    """Whether the batch kernels do the work for these operands: one of them a batch of at
    least KERNEL_MIN_BATCH matrices, and no matrix side beyond KERNEL_MAX_DIM (nor empty)."""
    big = False
    for a in arrays:
        if a.ndim > 2:
            p, q = a.shape[-2:]
            if not 0 < p <= KERNEL_MAX_DIM or not 0 < q <= KERNEL_MAX_DIM:
                return False
            big = big or a.size >= KERNEL_MIN_BATCH * p * q
    return big


def _batch_shape(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    """Broadcast of two batch shapes (numpy's rules; a mismatch is left to the operation)."""
    if a == b or not b:
        return a
    if not a:
        return b
    n = max(len(a), len(b))
    a, b = (1,) * (n - len(a)) + a, (1,) * (n - len(b)) + b
    return tuple(y if x == 1 else x for x, y in zip(a, b, strict=True))


def lanes_of(A: np.ndarray, nb: int) -> np.ndarray:
    """lanes(A) with the batch padded to `nb` dimensions (leading ones), so that lanes of
    operands with different batch dimensions broadcast like the matrices do."""
    if A.ndim - 2 < nb:
        A = A.reshape((1,) * (nb - A.ndim + 2) + A.shape)
    return lanes(A)


def lincomb(out: np.ndarray, coefs: list[float], rows: np.ndarray) -> None:
    """out = sum_l coefs[l] rows[l] for Python numbers coefs (a shared matrix's entries): zero
    terms are skipped and unit ones added without a multiplication (exact either way)."""
    first = True
    for c, v in zip(coefs, rows, strict=True):
        if c == 0.0:
            continue
        if first:
            if c == 1.0:
                np.copyto(out, v)
            elif c == -1.0:
                np.negative(v, out=out)
            else:
                np.multiply(v, c, out=out)
            first = False
        elif c == 1.0:
            out += v
        elif c == -1.0:
            out -= v
        else:
            out += c * v
    if first:
        out.fill(0.0)


def apply_shared(A: np.ndarray, X: np.ndarray, axis: int, out: np.ndarray) -> np.ndarray:
    """out[..., a, ...] = sum_b A[a, b] X[..., b, ...] along `axis`, for a small matrix A
    shared by the whole batch: a few whole-array operations with A's entries as Python
    numbers (zero terms skipped, unit ones added without a multiplication), the sums in
    einsum's order. Several times faster than einsum when X is a stack of matrices of every
    run (the joint covariance of the local filters, predicted with F of constant velocity:
    additions and copies only)."""
    Xm, om = np.moveaxis(X, axis, 0), np.moveaxis(out, axis, 0)
    for a, row in enumerate(A.tolist()):
        lincomb(om[a], row, Xm)
    return out


def mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B with matmul's broadcasting; large batches of small matrices by the batch kernel
    (result in the lanes layout): einsum's sum-of-products loops over the contiguous batch, or,
    for a shared factor of zeros and ones (a placement, F of constant velocity), only the
    additions and copies it makes."""
    if (A.size < KERNEL_MIN_BATCH and B.size < KERNEL_MIN_BATCH) or not kernels_for(A, B):
        return A @ B  # (a batch of KERNEL_MIN_BATCH matrices has at least as many entries)
    if A.ndim == 2 and _is_identity(A):  # the other factor itself (never written to)
        return B
    if B.ndim == 2 and _is_identity(B):
        return A
    batch = _batch_shape(A.shape[:-2], B.shape[:-2])
    nb = len(batch)
    X = buffer((A.shape[-2], B.shape[-1]), batch)
    if A.ndim == 2 and _unit_entries(A):  # X[i] = sum_l A[i, l] B[l]
        Bl = lanes_of(B, nb)
        for i, row in enumerate(A.tolist()):
            lincomb(X[i], row, Bl)
    elif B.ndim == 2 and _unit_entries(B):  # X[:, j] = sum_l A[:, l] B[l, j]
        Al = lanes_of(A, nb).swapaxes(0, 1)
        for j, col in enumerate(B.T.tolist()):
            lincomb(X[:, j], col, Al)
    elif A.ndim == 2:
        np.einsum("il,lj...->ij...", A, lanes_of(B, nb), out=X)
    elif B.ndim == 2:
        np.einsum("il...,lj->ij...", lanes_of(A, nb), B, out=X)
    else:
        np.einsum("il...,lj...->ij...", lanes_of(A, nb), lanes_of(B, nb), out=X)
    return unlanes(X)


def _is_identity(A: np.ndarray) -> bool:
    """Whether a small shared matrix is the identity (a product with it is its other factor)."""
    p, q = A.shape
    return p == q and p <= KERNEL_MAX_DIM and A.ravel().tolist() == _EYE[p]


_EYE = {p: np.eye(p).ravel().tolist() for p in range(1, KERNEL_MAX_DIM + 1)}


def _unit_entries(A: np.ndarray) -> bool:
    """Whether every entry of a small matrix is 0, 1 or -1."""
    return A.size <= 64 and all(v in (0.0, 1.0, -1.0) for v in A.ravel().tolist())


def mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A v on lanes: A (d, e) + batch (or a shared (d, e) matrix), v (e,) + batch; the result
    (d,) + batch. The executor's per-run step."""
    if A.ndim == 2 and _is_identity(A):
        return v
    if A.ndim == 2 and _unit_entries(A):
        out = buffer((A.shape[0],), v.shape[1:])
        for i, row in enumerate(A.tolist()):
            lincomb(out[i], row, v)
        return out
    if A.ndim == 2:
        return np.einsum("ij,j...->i...", A, v)
    return np.einsum("ij...,j...->i...", A, v)


def cholesky(A: np.ndarray, rtol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factor of lanes A (n, n) + batch (entries i >= j set) and whether each
    matrix's pivots are all above PIVOT_RTOL times their diagonal entries (False for NaN)."""
    n = A.shape[0]
    L = buffer(A.shape[:2], A.shape[2:])
    ok = _all_true(A.shape[2:])
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d = d - L[j, k] * L[j, k]
        least = (PIVOT_RTOL if rtol is None else rtol) * A[j, j]
        np.maximum(least, _TINY, out=least)  # a subnormal pivot has lost its digits
        ok &= d > least
        Ljj = L[j, j]
        np.sqrt(d, out=Ljj)  # NaN where d < 0: that matrix is redone by LAPACK
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s = s - L[i, k] * L[j, k]
            np.divide(s, Ljj, out=L[i, j])
    return L, ok


def cholesky_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with L L^T X = B, lanes: L (n, n) + batch, B (n, r) + batch."""
    n = L.shape[0]
    shape = B.shape[:2] + _batch_shape(L.shape[2:], B.shape[2:])
    X = buffer(shape[:2], shape[2:])
    tmp = np.empty_like(X[0])
    # the same operations in the same order as s = B[i] - L[i, 0] X[0] - ..., in place: a
    # temporary per term cost more than the arithmetic
    for i in range(n):
        Xi = X[i]
        np.copyto(Xi, B[i])
        for k in range(i):
            np.multiply(L[i, k], X[k], out=tmp)
            Xi -= tmp
        Xi /= L[i, i]
    for i in range(n - 1, -1, -1):
        Xi = X[i]
        for k in range(i + 1, n):
            np.multiply(L[k, i], X[k], out=tmp)
            Xi -= tmp
        Xi /= L[i, i]
    return X


def cholesky_inverse(L: np.ndarray) -> np.ndarray:
    """(L L^T)^-1 = W^T W with W = L^-1, lanes; computed on and above the diagonal and
    mirrored, so it is exactly symmetric."""
    n = L.shape[0]
    W = buffer(L.shape[:2], L.shape[2:], zeros=True)
    for i in range(n):
        np.divide(1.0, L[i, i], out=W[i, i])
        for j in range(i):
            s = L[i, j] * W[j, j]
            for k in range(j + 1, i):
                s = s + L[i, k] * W[k, j]
            np.divide(s, L[i, i], out=W[i, j])
            np.negative(W[i, j], out=W[i, j])
    X = buffer(L.shape[:2], L.shape[2:])
    for i in range(n):
        for j in range(i, n):
            s = W[j, i] * W[j, j]
            for k in range(j + 1, n):
                s = s + W[k, i] * W[k, j]
            X[i, j] = s
            if j > i:
                X[j, i] = s
    return X


def _lu_solve(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """X with A X = B by Gaussian elimination with partial pivoting (the row of the largest
    entry, the first of equals, as LAPACK's getrf), lanes: A (n, n) + batch, B (n, r) + batch.
    Also whether every pivot is above PIVOT_RTOL times the largest entry of its matrix."""
    n, r = A.shape[0], B.shape[1]
    batch = _batch_shape(A.shape[2:], B.shape[2:])
    W = buffer((n, n + r), batch)
    W[:, :n] = A
    W[:, n:] = B
    scale = np.abs(A[0, 0])
    for i in range(n):
        for j in range(n):
            if i or j:
                np.maximum(scale, np.abs(A[i, j]), out=scale)
    scale *= PIVOT_RTOL
    ok = _all_true(batch)
    for c in range(n):
        best = np.abs(W[c, c])
        for t in range(c + 1, n):  # the first largest |entry| of the column becomes the pivot
            a = np.abs(W[t, c])
            swap = a > best
            if swap.any():
                np.maximum(best, a, out=best)
                top = np.where(swap, W[t], W[c])
                W[t] = np.where(swap, W[c], W[t])
                W[c] = top
        ok &= best > scale
        ok &= best > _TINY
        p = W[c, c]
        for i in range(c + 1, n):
            W[i, c + 1 :] -= (W[i, c] / p) * W[c, c + 1 :]
    X = W[:, n:]
    for i in range(n - 1, -1, -1):
        s = X[i]
        for k in range(i + 1, n):
            s = s - W[i, k] * X[k]
        np.divide(s, W[i, i], out=X[i])
    return X, ok


def _finite(X: np.ndarray) -> np.ndarray:
    """Whether each matrix of lanes X is finite (a sum beyond the float range counts as not)."""
    return np.isfinite(X.sum(axis=(0, 1)))


def _redo(out: np.ndarray, bad: np.ndarray, compute: Callable[..., np.ndarray], *args) -> None:
    """out[bad] = compute(*(a[bad] for a in args)): the matrices a kernel could not do safely,
    by the reference routine, each array broadcast to the batch of `out` first."""
    if not bad.any():
        return
    batch = out.shape[:-2]
    idx = np.nonzero(np.broadcast_to(bad, batch))
    subs = [np.broadcast_to(a, batch + a.shape[-2:])[idx] for a in args]
    out[idx] = compute(*subs)


def solve_kernel(A: np.ndarray, B: np.ndarray, hermitian: bool, what: str) -> np.ndarray:
    nb = len(_batch_shape(A.shape[:-2], B.shape[:-2]))
    Al, Bl = lanes_of(A, nb), lanes_of(B, nb)
    with np.errstate(all="ignore"):
        if hermitian:
            L, ok = cholesky(Al)
            X = cholesky_solve(L, Bl)
        else:
            X, ok = _lu_solve(Al, Bl)
        ok = ok & _finite(X)  # (A may have fewer runs than B)
    out = unlanes(X)
    _redo(out, ~ok, lambda a, b: solve_lapack(a, b, hermitian, what), A, B)
    return out


def solve_spd_or_flag(
    A: np.ndarray, B: np.ndarray, rtol: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """A^-1 B for a batch of symmetric positive definite A by the Cholesky kernel, and
    whether each A could be factored safely (every pivot above `rtol`, default PIVOT_RTOL,
    times its diagonal entry): where not, the result is not a solution and the caller
    computes that matrix its own way. Fewer than KERNEL_MIN_BATCH by LAPACK (`_spd_lapack`):
    the kernel makes ~n^3 numpy calls whatever the batch (a one-run nonlinear log's instant)."""
    batch = _batch_shape(A.shape[:-2], B.shape[:-2])
    if not many_matrices(batch):
        got = _spd_lapack(A, B, PIVOT_RTOL if rtol is None else rtol)
        if got is not None:
            return got
    with np.errstate(all="ignore"):
        L, ok = cholesky(lanes_of(A, len(batch)), rtol)
        X = cholesky_solve(L, lanes_of(B, len(batch)))
        ok = ok & _finite(X)  # (A may have fewer runs than B)
    return unlanes(X), ok


def _spd_lapack(A: np.ndarray, B: np.ndarray, rtol: float) -> tuple[np.ndarray, ...] | None:
    """`solve_spd_or_flag` by LAPACK's Cholesky (pivots L_jj^2) and LU solve for a few matrices;
    None where one is not positive definite (the kernel then flags each on its own)."""
    with np.errstate(all="ignore"):
        try:
            L = np.linalg.cholesky(A)
            X = np.linalg.solve(A, B)
        except np.linalg.LinAlgError:
            return None
        pivots = np.square(np.diagonal(L, axis1=-2, axis2=-1))
        least = np.maximum(rtol * np.diagonal(A, axis1=-2, axis2=-1), _TINY)
        ok = (pivots > least).all(axis=-1) & np.isfinite(X).all(axis=(-2, -1))
    return X, np.broadcast_to(ok, X.shape[:-2]).copy()


def spd_inv_kernel(
    A: np.ndarray, reference: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of a batch of SPD matrices by Cholesky, the unsafe ones by `reference`; also
    whether each matrix went through the kernel."""
    with np.errstate(all="ignore"):
        L, ok = cholesky(lanes(A))
        X = cholesky_inverse(L)
        ok = ok & _finite(X)  # (A may have fewer runs than B)
    out = unlanes(X)
    _redo(out, ~ok, reference, A)
    return out, ok
