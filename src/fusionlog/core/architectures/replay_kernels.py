"""The per-instant loops of the plan-free replay (`replay_filters`), compiled by numba.

A recorded log's Kalman recursions are sequential: instant k needs instant k-1's covariance.
As numpy calls on a batch of small matrices they cost ~20 calls of ~1-3 us per instant
whatever the size of the matrices (issue 34: 10^6 instants, ~700 s of CPU); compiled, an
instant of the paper's seven architectures costs about a microsecond
(`benchmarks/bench_replay_kernels.py`). Each kernel writes into arrays its caller allocates,
and loops entry by entry over the small matrices (n, m of a few states and sensors), in the
order of the formulas: the products and sums are those of the numpy loops they replace, not
their bits (BLAS sums in another order), which is why tests compare this path with the plans
to a tolerance following from the conditioning and compare a log in blocks of time with the
same log whole bit for bit (the same kernel on the same numbers).

`error_model="numpy"`: a division by zero gives inf or NaN, as numpy does under
`np.errstate(all="ignore")`, for the callers' finiteness checks to hand the log to the plans.
A singular matrix (an exactly zero pivot, LAPACK getrf's info > 0) is reported by the instant
it occurs at, for the caller to raise `np.linalg.LinAlgError` as numpy would.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["affine", "backward", "backward_vectors", "bank", "joint"]

_jit = njit(cache=True, error_model="numpy", nogil=True)


@_jit
def _solve(A, B, X, W):  # pragma: no cover - compiled
    """X = A^-1 B by LU with partial pivoting (as LAPACK's getrf/getrs, numpy's solve): A (m,
    m), B (m, q), W (m, m) the work space; False where a pivot is exactly zero."""
    m, q = A.shape[0], B.shape[1]
    for i in range(m):
        for j in range(m):
            W[i, j] = A[i, j]
        for j in range(q):
            X[i, j] = B[i, j]
    for c in range(m):
        p, best = c, abs(W[c, c])
        for r in range(c + 1, m):
            if abs(W[r, c]) > best:
                p, best = r, abs(W[r, c])
        if W[p, c] == 0.0:
            return False
        if p != c:
            for j in range(m):
                W[c, j], W[p, j] = W[p, j], W[c, j]
            for j in range(q):
                X[c, j], X[p, j] = X[p, j], X[c, j]
        for r in range(c + 1, m):
            f = W[r, c] / W[c, c]
            for j in range(c + 1, m):
                W[r, j] -= f * W[c, j]
            for j in range(q):
                X[r, j] -= f * X[c, j]
    for c in range(m - 1, -1, -1):
        for j in range(q):
            v = X[c, j]
            for i in range(c + 1, m):
                v -= W[c, i] * X[i, j]
            X[c, j] = v / W[c, c]
    return True


@_jit
def _mul(A, B, out):  # pragma: no cover - compiled
    """out = A B."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            v = 0.0
            for k in range(A.shape[1]):
                v += A[i, k] * B[k, j]
            out[i, j] = v


@_jit
def _mul_t(A, B, out):  # pragma: no cover - compiled
    """out = A B'."""
    _mul(A, B.T, out)


@_jit
def _sym_into(A, out):  # pragma: no cover - compiled
    """out = (A + A') / 2, as `linalg.sym`."""
    for i in range(A.shape[0]):
        for j in range(A.shape[0]):
            out[i, j] = 0.5 * (A[i, j] + A[j, i])


@_jit
def _sandwich(A, P, out, T):  # pragma: no cover - compiled
    """out = (A P) A' (T the work space for A P)."""
    _mul(A, P, T)
    _mul_t(T, A, out)


@_jit
def bank(src, h, P0, F, Q, first, Hm, Rm, P, KT, IKH, Yh):  # pragma: no cover - compiled
    """`replay_filters.run_bank`'s loop: slot b of Hm, Rm (K+1, B, m, .) starts each instant from
    the carried covariance src[b] (P0 (C, n, n) before instant 0), predicted by F[k - first],
    Q[k - first] at the instants k >= first (prediction sym(F P F' + G Q G')); gain K' = sym(H
    P H' + R)^-1 H P (eq. 17) into KT, I - K H into IKH, the Joseph form of eq. (18) into P.
    h >= 0: HKF's slots h.. (its fused prediction, then a local update per sensor), their
    informations sym(P^-1) into Yh (K+1, S+1, n, n) and the fused P = sym(((1 - S) Y_pred +
    Y_1 + ... + Y_S)^-1) (eqs. 36-38) in slot h's place. Returns -1, or the instant of a
    singular matrix."""
    K1, B, m, n = Hm.shape
    C = P0.shape[0]
    Pc = P0.copy()
    Pp = np.empty((C, n, n))
    A, T, T2 = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    HP, Sk, Ss, W = np.empty((m, n)), np.empty((m, m)), np.empty((m, m)), np.empty((m, m))
    KR = np.empty((n, m))
    Wn, eye = np.empty((n, n)), np.eye(n)
    S = B - h - 1 if h >= 0 else 0
    for k in range(K1):
        for c in range(C):
            if k >= first:
                _sandwich(F[k - first], Pc[c], A, T)
                A += Q[k - first]
                _sym_into(A, Pp[c])
            else:
                Pp[c] = Pc[c]
        for b in range(B):
            Pb, H, R = Pp[src[b]], Hm[k, b], Rm[k, b]
            X, G, Pk = KT[k, b], IKH[k, b], P[k, b]
            _mul(H, Pb, HP)
            _mul_t(HP, H, Sk)
            Sk += R
            _sym_into(Sk, Ss)
            if not _solve(Ss, HP, X, W):
                return k
            for i in range(n):  # I - K H, K = X'
                for j in range(n):
                    v = 0.0
                    for r in range(m):
                        v += X[r, i] * H[r, j]
                    G[i, j] = eye[i, j] - v
            _sandwich(G, Pb, A, T)
            for i in range(n):  # K R
                for j in range(m):
                    v = 0.0
                    for r in range(m):
                        v += X[r, i] * R[r, j]
                    KR[i, j] = v
            _mul(KR, X, T2)
            A += T2
            _sym_into(A, Pk)
        if h >= 0:
            for i in range(S + 1):
                if not _solve(P[k, h + i], eye, Wn, T):
                    return k
                _sym_into(Wn, Yh[k, i])
            for i in range(n):  # (1 - S) Y_pred + Y_1 + ... + Y_S, in that order
                for j in range(n):
                    v = Yh[k, 0, i, j] * (1.0 - S)
                    for r in range(1, S + 1):
                        v += Yh[k, r, i, j]
                    A[i, j] = v
            if not _solve(A, eye, Wn, T):
                return k
            _sym_into(Wn, P[k, h])
        Pc[:] = P[k, :C]  # the carried slots: all, or up to HKF's fused one
    return -1


@_jit
def affine(A, b, x0, out):  # pragma: no cover - compiled
    """`replay_filters.affine_recursion`'s loop: out[k] = A[k] out[k-1] + b[k] (out[-1] = x0),
    for each of f stacked recursions: A (K+1, f, n, n), b (K+1, f, n), x0 (f, n)."""
    K1, f, n = b.shape
    x = x0.copy()
    for k in range(K1):
        for g in range(f):
            for i in range(n):
                v = 0.0
                for j in range(n):
                    v += A[k, g, i, j] * x[g, j]
                out[k, g, i] = v + b[k, g, i]
        x[:] = out[k]


@_jit
def joint(A, C, J0, out):  # pragma: no cover - compiled
    """`replay_filters.joint_recursion`'s loop: out[k] = sym(A_k out[k-1] A_k' + C_k) from
    out[-1] = J0, A and C (K+1, N, N)."""
    K1, N = C.shape[0], C.shape[1]
    J = J0.copy()
    T, M = np.empty((N, N)), np.empty((N, N))
    for k in range(K1):
        _sandwich(A[k], J, M, T)
        M += C[k]
        _sym_into(M, out[k])
        J[:] = out[k]


@_jit
def backward(W, F, Q, L, Smat):  # pragma: no cover - compiled
    """`replay_filters.backward_information`'s loop, from Smat[-1] (set by the caller) down:
    S^+ = sym(S_{k+1} + W_{k+1}), L_k = F' (I + S^+ Q)^-1 as (solve((I + S^+ Q)', F))', S_k =
    sym(L_k S^+ F) (eqs. 25-28). Returns -1, or the instant of a singular matrix."""
    K1, n = W.shape[0], W.shape[-1]
    Sp, Bt, X, T, A, Wk = np.empty((6, n, n))
    for k in range(K1 - 2, -1, -1):
        for i in range(n):
            for j in range(n):
                A[i, j] = Smat[k + 1, i, j] + W[k + 1, i, j]
        _sym_into(A, Sp)
        _mul(Sp, Q[k], T)
        for i in range(n):  # (I + S^+ Q)'
            for j in range(n):
                Bt[i, j] = T[j, i] + (1.0 if i == j else 0.0)
        if not _solve(Bt, F[k], X, Wk):
            return k
        for i in range(n):
            for j in range(n):
                L[k, i, j] = X[j, i]
        _mul(L[k], Sp, T)
        _mul(T, F[k], A)
        _sym_into(A, Smat[k])
    return -1


@_jit
def backward_vectors(L, c, out):  # pragma: no cover - compiled
    """`replay_filters.backward_means`' loop, from out[-1] (set by the caller) down: out[k] =
    L_k (out[k+1] + c[k+1])."""
    K1, n = c.shape
    for k in range(K1 - 2, -1, -1):
        for i in range(n):
            v = 0.0
            for j in range(n):
                v += L[k, i, j] * (out[k + 1, j] + c[k + 1, j])
            out[k, i] = v
