"""The compiled MSC-GMF kernel `probe_compiled.py` measures (needs numba; not part of fusionlog).

Runs innermost in every loop, in blocks of CHUNK, so that LLVM vectorises over them; the small
matrices' loops have their sizes at run time (any n and number of scalar sensors).
"""

import numpy as np
from numba import njit

#: Runs per block: the kernel's scratch for a block stays in the L2 cache.
CHUNK = 256


@njit(cache=True, error_model="numpy")
def msc_gmf(z, F, Q, H, R, x0, P0, out_x, out_P, regular):
    """MSC-GMF per run: local KFs (Joseph-equivalent scalar updates), J of eq. (35) block by
    block, C = (E^T J^-1 E)^-1 E^T J^-1 by Cholesky (eqs. 6-7 where J is regular)."""
    M, K1, S = z.shape
    n = F.shape[0]
    N = S * n
    x = np.empty((N, CHUNK))
    xs = np.empty((n, CHUNK))
    zz = np.empty((S, CHUNK))
    J = np.empty((N, N, CHUNK))
    T = np.empty((N, N, CHUNK))
    Kg = np.empty((S, n, CHUNK))
    L = np.empty((N, N, CHUNK))
    X = np.empty((N, n, CHUNK))
    W = np.empty((n, n, CHUNK))
    C = np.empty((n, N, CHUNK))
    sv = np.empty(CHUNK)
    iv = np.empty(CHUNK)
    hv = np.empty(CHUNK)
    ok = np.empty(CHUNK)
    for c0 in range(0, M, CHUNK):
        nl = min(M, c0 + CHUNK) - c0
        for a in range(N):
            for l in range(nl):
                x[a, l] = x0[a % n]
            for b in range(N):
                v = P0[a % n, b % n]
                for l in range(nl):
                    J[a, b, l] = v
        for k in range(K1):
            for j in range(S):
                for l in range(nl):
                    zz[j, l] = z[c0 + l, k, j]
            if k > 0:  # predict: x_j <- F x_j, J_ab <- F J_ab F^T + Q
                for j in range(S):
                    for i in range(n):
                        for l in range(nl):
                            xs[i, l] = 0.0
                        for q in range(n):
                            f = F[i, q]
                            for l in range(nl):
                                xs[i, l] += f * x[j * n + q, l]
                    for i in range(n):
                        for l in range(nl):
                            x[j * n + i, l] = xs[i, l]
                for a in range(N):
                    i0 = (a // n) * n
                    for b in range(N):
                        for l in range(nl):
                            T[a, b, l] = 0.0
                        for q in range(n):
                            f = F[a - i0, q]
                            for l in range(nl):
                                T[a, b, l] += f * J[i0 + q, b, l]
                for a in range(N):
                    for b in range(N):
                        j0 = (b // n) * n
                        qv = Q[a % n, b % n]
                        for l in range(nl):
                            J[a, b, l] = qv
                        for q in range(n):
                            f = F[b - j0, q]
                            for l in range(nl):
                                J[a, b, l] += T[a, j0 + q, l] * f
            for j in range(S):  # local updates; a missing measurement: gain 0
                o = j * n
                for l in range(nl):
                    sv[l] = R[j]
                for i in range(n):
                    for l in range(nl):
                        Kg[j, i, l] = 0.0
                    for q in range(n):
                        h = H[j, q]
                        for l in range(nl):
                            Kg[j, i, l] += J[o + i, o + q, l] * h
                    for l in range(nl):
                        sv[l] += H[j, i] * Kg[j, i, l]
                for l in range(nl):
                    hv[l] = 0.0
                for i in range(n):
                    for l in range(nl):
                        hv[l] += H[j, i] * x[o + i, l]
                for l in range(nl):
                    zl = zz[j, l]
                    miss = zl != zl
                    iv[l] = 0.0 if miss else (zl - hv[l]) / sv[l]
                    sv[l] = 0.0 if miss else 1.0 / sv[l]
                for i in range(n):
                    for l in range(nl):
                        x[o + i, l] += Kg[j, i, l] * iv[l]
                        Kg[j, i, l] *= sv[l]
            # eq. (35): J <- A J A^T + blockdiag(K_j R_j K_j^T), A = blockdiag(I - K_j h_j)
            for a in range(N):
                ja = a // n
                for b in range(N):
                    for l in range(nl):
                        hv[l] = 0.0
                    for q in range(n):
                        h = H[ja, q]
                        for l in range(nl):
                            hv[l] += h * J[ja * n + q, b, l]
                    for l in range(nl):
                        T[a, b, l] = J[a, b, l] - Kg[ja, a - ja * n, l] * hv[l]
            for a in range(N):
                ja = a // n
                for b in range(a, N):
                    jb = b // n
                    ib = b - jb * n
                    for l in range(nl):
                        hv[l] = 0.0
                    for q in range(n):
                        h = H[jb, q]
                        for l in range(nl):
                            hv[l] += T[a, jb * n + q, l] * h
                    if ja == jb:
                        r = R[ja]
                        for l in range(nl):
                            J[a, b, l] = (
                                T[a, b, l]
                                - hv[l] * Kg[jb, ib, l]
                                + Kg[ja, a - ja * n, l] * Kg[jb, ib, l] * r
                            )
                    else:
                        for l in range(nl):
                            J[a, b, l] = T[a, b, l] - hv[l] * Kg[jb, ib, l]
            for a in range(N):
                for b in range(a):
                    for l in range(nl):
                        J[a, b, l] = J[b, a, l]
            # GMF weights: J = L L^T, X = J^-1 E, W = E^T X, C = W^-1 X^T, P = C J C^T
            for l in range(nl):
                ok[l] = 1.0
            for i in range(N):
                for jj in range(i + 1):
                    for l in range(nl):
                        hv[l] = J[i, jj, l]
                    for q in range(jj):
                        for l in range(nl):
                            hv[l] -= L[i, q, l] * L[jj, q, l]
                    if i == jj:
                        for l in range(nl):
                            bad = hv[l] <= 1e-6 * J[i, i, l]
                            ok[l] = 0.0 if bad else ok[l]
                            L[i, i, l] = np.sqrt(1.0 if bad else hv[l])
                    else:
                        for l in range(nl):
                            L[i, jj, l] = hv[l] / L[jj, jj, l]
            for c in range(n):
                for i in range(N):
                    e = 1.0 if i % n == c else 0.0
                    for l in range(nl):
                        hv[l] = e
                    for q in range(i):
                        for l in range(nl):
                            hv[l] -= L[i, q, l] * X[q, c, l]
                    for l in range(nl):
                        X[i, c, l] = hv[l] / L[i, i, l]
                for i in range(N - 1, -1, -1):
                    for l in range(nl):
                        hv[l] = X[i, c, l]
                    for q in range(i + 1, N):
                        for l in range(nl):
                            hv[l] -= L[q, i, l] * X[q, c, l]
                    for l in range(nl):
                        X[i, c, l] = hv[l] / L[i, i, l]
            for i in range(n):
                for c in range(n):
                    for l in range(nl):
                        W[i, c, l] = 0.0
                    for j in range(S):
                        for l in range(nl):
                            W[i, c, l] += X[j * n + i, c, l]
            # C = W^-1 X^T through W's Cholesky factor (in place in W's lower triangle)
            for i in range(n):
                for jj in range(i + 1):
                    for l in range(nl):
                        hv[l] = W[i, jj, l]
                    for q in range(jj):
                        for l in range(nl):
                            hv[l] -= W[i, q, l] * W[jj, q, l]
                    if i == jj:
                        for l in range(nl):
                            W[i, i, l] = np.sqrt(hv[l])
                    else:
                        for l in range(nl):
                            W[i, jj, l] = hv[l] / W[jj, jj, l]
            for b in range(N):
                for i in range(n):
                    for l in range(nl):
                        hv[l] = X[b, i, l]
                    for q in range(i):
                        for l in range(nl):
                            hv[l] -= W[i, q, l] * C[q, b, l]
                    for l in range(nl):
                        C[i, b, l] = hv[l] / W[i, i, l]
                for i in range(n - 1, -1, -1):
                    for l in range(nl):
                        hv[l] = C[i, b, l]
                    for q in range(i + 1, n):
                        for l in range(nl):
                            hv[l] -= W[q, i, l] * C[q, b, l]
                    for l in range(nl):
                        C[i, b, l] = hv[l] / W[i, i, l]
            for i in range(n):
                for l in range(nl):
                    hv[l] = 0.0
                for b in range(N):
                    for l in range(nl):
                        hv[l] += C[i, b, l] * x[b, l]
                for l in range(nl):
                    out_x[c0 + l, k, i] = hv[l]
            for i in range(n):
                for b in range(N):
                    for l in range(nl):
                        T[i, b, l] = 0.0
                    for a in range(N):
                        for l in range(nl):
                            T[i, b, l] += C[i, a, l] * J[a, b, l]
            for i in range(n):
                for c in range(n):
                    for l in range(nl):
                        hv[l] = 0.0
                    for b in range(N):
                        for l in range(nl):
                            hv[l] += T[i, b, l] * C[c, b, l]
                    for l in range(nl):
                        out_P[c0 + l, k, i, c] = hv[l]
            for l in range(nl):
                regular[c0 + l, k] = ok[l] > 0.0
