"""The EKF's prediction (linear motion) and measurement update of many runs at once, on lanes
(`core.kernels`: every matrix entry one contiguous vector over the runs).

Prediction with one F for every run:  C = P F^T,  P- = F C + Q, each entry a sum over the
nonzero entries of F only (`kernels.lincomb`; constant velocity's F is half zeros).

Update with H nonzero only on the state columns q (a radar sees x and y, not the velocities),
everything through the |q| x |q| block (2 x 2 for a position) instead of n x n products:

    B = H[:, q] P[q, q],   S = B H[:, q]^T + R,   V = S^-1 H[:, q]  (Cholesky of S),
    K = P H^T S^-1 = P[:, q] V^T,   x+ = x + K y = x + P[:, q] (V^T y),
    P+ = (I - K H) P (I - K H)^T + K R K^T  (Joseph form)
       = P - P[:, q] T P[q, :]   with   T = G + G^T - G^T P[q, q] G - V^T R V,  G = H[:, q]^T V,

since K H = P[:, q] G^T on the columns q. The second line is the Joseph form of the gain
K = P[:, q] V^T as computed (its terms expanded, no identity of the exact gain used), so it
keeps the Joseph form's property: an error E in V moves T by E^T S E only, second order
(with V = S^-1 H + E, T = H^T S^-1 H - E^T S E).

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
    in the lanes layout. P- = F C + Q is computed on and above the diagonal and mirrored, so
    it is exactly symmetric (as P+ is)."""
    n, M = F.shape[0], P.shape[0]
    Pt = lanes(P).swapaxes(0, 1)  # Pt[l] = column l of P, (n, M)
    C = np.empty((n, n, M))
    for j in range(n):
        lincomb(C[:, j], F[j].tolist(), Pt)
    Pp = np.empty((n, n, M))
    for i in range(n):
        lincomb(Pp[i, i:], F[i].tolist(), C[:, i:])
        for j, v in enumerate(Q[i, i:].tolist(), i):
            if v != 0.0:  # adding a zero changes nothing
                Pp[i, j] += v
        Pp[i + 1 :, i] = Pp[i, i + 1 :]
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
    """(x+ (M, n), P+ lanes (n, n, M), V = S^-1 H[:, q] lanes (m, |q|, M)) of the module
    docstring's update: x (M, n), Pl the lanes of P (n, n, M), Hq the columns q of H on lanes
    (m, |q|, M), R shared (m, m) or lanes (m, m, M), y the innovation on lanes (m, M). The
    gain is K = P[:, q] V^T (`gain_lanes`). `work` keeps the temporaries from one call to the
    next (a filter's instants): fresh arrays are fresh pages, a page fault each on first
    touch, which cost as much as the arithmetic."""
    n, M = Pl.shape[0], Pl.shape[-1]
    m, nq = Hq.shape[0], len(q)
    work = {} if work is None else work
    Pq = [Pl[c] for c in q]  # rows q of P, which are its columns q: (n, M) each
    Hcols = [Hq[:, a] for a in range(nq)]  # (m, M) each
    tm = _scratch(work, "tm", (m, M))
    tv = _scratch(work, "tv", (M,))
    # B = H[:, q] P[q, q]; S = B H[:, q]^T + R on and below the diagonal (what the Cholesky
    # kernel reads), a column at a time: the same products summed in the same order as
    # H (P H^T) entry by entry, so S is bit for bit what it was
    B = _scratch(work, "B", (m, nq, M))
    for b in range(nq):
        _combine(B[:, b], [P[q[b]] for P in Pq], Hcols, tm)
    S = _scratch(work, "S", (m, m, M))
    for s in range(m):
        _combine(S[s:, s], [B[s, a] for a in range(nq)], [h[s:] for h in Hcols], tm[: m - s])
        if R.ndim == 3:
            S[s:, s] += R[s:, s]
        else:
            for r in range(s, m):
                if R[r, s] != 0.0:  # adding a zero changes nothing
                    S[r, s] += R[r, s]
    with np.errstate(all="ignore"):
        L, ok = cholesky(S)
        V = cholesky_solve(L, Hq)  # (m, |q|, M) = S^-1 H[:, q]
    if not ok.all():  # a badly conditioned S: those runs by LAPACK's solve (or pinv)
        bad = np.flatnonzero(~ok)
        for r in range(m):
            S[r, r + 1 :] = S[r + 1 :, r]
        Sb, Bb = sym(unlanes(S)[bad]), unlanes(Hq)[bad]
        V[..., bad] = lanes(solve(Sb, Bb, hermitian=True, what="the innovation covariance"))
    # G = H[:, q]^T V (not symmetric to the last bit), W = V^T R V, g = V^T y
    G = _scratch(work, "G", (nq, nq, M))
    for a in range(nq):
        for b in range(nq):
            np.multiply(Hcols[a], V[:, b], out=tm)
            np.add.reduce(tm, axis=0, out=G[a, b])
    RV = _scratch(work, "RV", (m, nq, M))  # R V
    for r in range(m):
        if R.ndim == 2:
            lincomb(RV[r], R[r].tolist(), V)
        else:
            _combine(RV[r], list(R[r]), list(V), _scratch(work, "tq", (nq, M)))
    T = _scratch(work, "T", (nq, nq, M))
    U = _scratch(work, "U", (nq, nq, M))  # P[q, q] G
    for c in range(nq):
        for b in range(nq):
            _combine(U[c, b], [G[d, b] for d in range(nq)], [P[q[c]] for P in Pq], tv)
    for a in range(nq):  # T on and above the diagonal, mirrored: G + G^T - G^T P[q, q] G - W
        for b in range(a, nq):
            t = T[a, b]
            np.multiply(V[:, a], RV[:, b], out=tm)
            np.add.reduce(tm, axis=0, out=t)
            for c in range(nq):
                np.multiply(G[c, a], U[c, b], out=tv)
                t += tv
            np.subtract(G[a, b], t, out=t)
            t += G[b, a]
            if b > a:
                T[b, a] = t
    # P+ = P - P[:, q] T P[q, :], on and above the diagonal and mirrored
    Z = _scratch(work, "Z", (nq, n, M))  # Z[b] = column b of P[:, q] T
    row = _scratch(work, "row", (n, M))
    for b in range(nq):
        _combine(Z[b], [T[a, b] for a in range(nq)], Pq, row)
    Pu = np.empty((n, n, M))  # returned: its own memory
    for i in range(n):
        out, tmp = Pu[i, i:], row[: n - i]
        for b in range(nq):
            np.multiply(Z[b, i], Pq[b][i:], out=tmp)
            np.subtract(Pl[i, i:] if b == 0 else out, tmp, out=out)
        Pu[i + 1 :, i] = Pu[i, i + 1 :]
    g = _scratch(work, "g", (nq, M))  # V^T y
    for a in range(nq):
        np.multiply(V[:, a], y, out=tm)
        np.add.reduce(tm, axis=0, out=g[a])
    dx = np.empty((n, M))
    _combine(dx, list(g), Pq, row)
    return x + dx.T, Pu, V


def gain_lanes(Pl: np.ndarray, q: list[int], V: np.ndarray) -> np.ndarray:
    """K^T = V P[q, :] on lanes (m, n, M): the gain K = P[:, q] V^T of `joseph_update`, for
    the architectures that propagate errors through it (the CKF never asks)."""
    m, nq = V.shape[:2]
    Kt = np.empty((m,) + Pl.shape[1:])
    tmp = np.empty(Pl.shape[1:])
    for r in range(m):
        _combine(Kt[r], [V[r, a] for a in range(nq)], [Pl[c] for c in q], tmp)
    return Kt


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
