"""The EKF's prediction (linear motion) and measurement update of many runs at once, on lanes
(`core.kernels`: every matrix entry one contiguous vector over the runs).

Prediction with one F for every run:  C = P F^T,  P- = sym(F C + Q), each entry a sum over the
nonzero entries of F only (`kernels.lincomb`; constant velocity's F is half zeros).

Update with H nonzero only on the state columns q (a radar sees x and y, not the velocities):

    H P = H[:, q] P[q],   S = H[:, q] (H P)[:, q]^T + R,   K^T = S^-1 H P  (Cholesky of S),
    x+ = x + K y,
    P+ = (I - K H) P (I - K H)^T + K R K^T  (Joseph form)
       = A P - (A P)[:, q] (K H[:, q])^T + (K R) K^T   with   A P = P - (K H[:, q]) P[q].

Each product is a handful of elementwise operations over the runs into preallocated arrays
(`out=`): numpy's einsum on these shapes, or its stacked matmul and solve on (M, 4, 4)
arrays, spend most of their time on temporaries and per-matrix overhead. P+ is computed on and
above the diagonal and mirrored, so it is exactly symmetric (as `core.kernels.cholesky_inverse`
makes its inverses). P is symmetric, so its rows q stand for its columns q.
"""

from __future__ import annotations

import numpy as np

from ..kernels import cholesky, cholesky_solve, lanes, lincomb, unlanes
from ..linalg import solve, sym


def linear_prediction(P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P-, C) of the module docstring for P (M, n, n) and shared F, Q (n, n); both returned
    in the lanes layout. P- is `linalg.sym` of F C + Q, entry by entry: the same numbers."""
    n, M = F.shape[0], P.shape[0]
    Pt = lanes(P).swapaxes(0, 1)  # Pt[l] = column l of P, (n, M)
    C = np.empty((n, n, M))
    for j in range(n):
        lincomb(C[:, j], F[j].tolist(), Pt)
    Pp = np.empty((n, n, M))
    for i in range(n):
        lincomb(Pp[i], F[i].tolist(), C)
        for j, v in enumerate(Q[i].tolist()):
            if v != 0.0:  # adding a zero changes nothing
                Pp[i, j] += v
    for i in range(n):
        for j in range(i + 1, n):
            s = Pp[i, j]
            s += Pp[j, i]
            s *= 0.5
            Pp[j, i] = s
    return unlanes(Pp), unlanes(C)


def joseph_update(
    x: np.ndarray,
    Pl: np.ndarray,
    Hq: np.ndarray,
    q: list[int],
    R: np.ndarray,
    y: np.ndarray,
    work: dict | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x+ (M, n), P+ lanes (n, n, M), K^T lanes (m, n, M)) of the module docstring's update:
    x (M, n), Pl the lanes of P (n, n, M), Hq the columns q of H on lanes (m, |q|, M), R shared
    (m, m) or lanes (m, m, M), y the innovation on lanes (m, M). `work` keeps the temporaries
    from one call to the next (a filter's instants): fresh arrays of a megabyte each are fresh
    pages, a page fault each on first touch, which cost as much as the arithmetic."""
    n, M = Pl.shape[0], Pl.shape[-1]
    m = Hq.shape[0]
    work = {} if work is None else work
    row = _scratch(work, "row", (n, M))  # one row's products
    HP = _scratch(work, "HP", (m, n, M))  # H P = (P H^T)^T: the right-hand side of the solve
    for r in range(m):
        _combine(HP[r], [Hq[r, a] for a in range(len(q))], [Pl[c] for c in q], row)
    S = _scratch(work, "S", (m, m, M))
    for r in range(m):  # the lower triangle: all the Cholesky kernel reads
        for s in range(r + 1):
            _combine(S[r, s], [Hq[r, a] for a in range(len(q))], [HP[s, c] for c in q], row[0])
            S[r, s] += R[r, s]
    with np.errstate(all="ignore"):
        L, ok = cholesky(S)
        Kt = cholesky_solve(L, HP)  # (m, n, M) = S^-1 H P = K^T
    if not ok.all():  # a badly conditioned S: those runs by LAPACK's solve (or pinv)
        bad = np.flatnonzero(~ok)
        for r in range(m):
            S[r, r + 1 :] = S[r + 1 :, r]
        Sb, Bb = sym(unlanes(S)[bad]), unlanes(HP)[bad]
        Kt[..., bad] = lanes(solve(Sb, Bb, hermitian=True, what="the innovation covariance"))
    KH = _scratch(work, "KH", (len(q), n, M))  # KH[a] = column a of K H[:, q]
    for a in range(len(q)):
        _combine(KH[a], [Hq[r, a] for r in range(m)], list(Kt), row)
    KRt = _scratch(work, "KRt", (m, n, M))  # (K R)^T
    for s in range(m):
        if R.ndim == 2:
            lincomb(KRt[s], R[:, s].tolist(), Kt)
        else:
            _combine(KRt[s], [R[r, s] for r in range(m)], list(Kt), row)
    AP = _scratch(work, "AP", (n, n, M))
    Pu = np.empty((n, n, M))  # returned: its own memory
    for i in range(n):
        AP[i] = Pl[i]
        for a, c in enumerate(q):
            np.multiply(KH[a, i], Pl[c], out=row)
            AP[i] -= row
    for i in range(n):
        out, tmp = Pu[i, i:], row[: n - i]
        np.copyto(out, AP[i, i:])
        for a, c in enumerate(q):
            np.multiply(AP[i, c], KH[a, i:], out=tmp)
            out -= tmp
        for s in range(m):
            np.multiply(KRt[s, i], Kt[s, i:], out=tmp)
            out += tmp
        Pu[i + 1 :, i] = Pu[i, i + 1 :]
    dx = np.empty((n, M))
    _combine(dx, list(y), list(Kt), row)
    return x + dx.T, Pu, Kt


def _scratch(work: dict, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """The workspace's array `name` of this shape (uninitialised), made on first use."""
    a = work.get(name)
    if a is None or a.shape != shape:
        a = work[name] = np.empty(shape)
    return a


def _combine(out: np.ndarray, coefs: list, rows: list, tmp: np.ndarray) -> None:
    """out = sum_l coefs[l] rows[l], coefs vectors over the runs (M,) broadcast against rows
    (..., M), through the workspace tmp (out's shape)."""
    np.multiply(rows[0], coefs[0], out=out)
    for c, v in zip(coefs[1:], rows[1:], strict=True):
        np.multiply(v, c, out=tmp)
        out += tmp
