"""The log-likelihood of one recorded run (a replayed log) through the Kalman filter's
innovations, for C candidate noise models at once: `likelihood.loglik`'s sum

    log p(z_0, ..., z_K) = -1/2 sum_k [ log det S_k + nu_k' S_k^-1 nu_k + d_k log 2 pi ]

(Schweppe 1965; Harvey 1989, sec. 3.4) on the path `architectures.replay_filters` takes for a
one-run filter: the instant loop holds only what feeds back into the recursion, with a fixed,
small number of numpy calls per instant, and what does not (the log-determinants and the PD
check of every S_k, the quadratic forms) is computed afterwards for all instants at once.

A single log has one pattern of present readings, so the rows each instant uses, their H
and (when R does not vary by message) their R are worked out once per distinct pattern and
the loop only indexes them. Per instant, for the C candidates together:

    x- = F x,  P- = F P F' + Q,                             (prediction, eq. 14-15)
    nu = z_rows - H_rows x-,  S = H_rows P- H_rows' + R_rows,
    [K' | S^-1 nu] = S^-1 [H_rows P- | nu]                  (one solve: gain of eq. 17)
    x = x- + P- H' S^-1 nu,  P = sym(P- - P- H' K')          (update, eq. 18)

which are the formulas of `likelihood._block` (its Cholesky-whitened form is the same
algebra). A candidate whose S is singular somewhere makes the batched solve fail: the caller
then takes the general path, which names the failing candidates (-inf) one by one.
"""

from __future__ import annotations

import numpy as np

from .model import System

__all__ = ["loglik_one_run"]

LOG_2PI = float(np.log(2.0 * np.pi))
#: Instants whose S_k are kept before they are factorised together: a few megabytes whatever
#: the length of the log.
FLUSH = 1024


def loglik_one_run(
    system: System, z: np.ndarray, P0: np.ndarray, Q: np.ndarray, q_at: np.ndarray,
    R: np.ndarray, r_at: np.ndarray, H_all: np.ndarray, cholesky,
) -> np.ndarray:  # fmt: skip
    """The log-likelihood (C,) of one run's readings z (K+1, m) (NaN: absent; the truth's
    columns, if any, at the end, with zero R) for candidates P0 (C, n, n), Q (C or 1, U, n, n)
    with q_at (K,), R (C, V, m, m) with r_at (K+1,) and the stacked H_all (m, n) of a linear
    `system`. `cholesky` is `likelihood._cholesky` (factors and the candidates refused).
    Raises np.linalg.LinAlgError where a candidate's S is singular."""
    K1, m = z.shape
    C, n = P0.shape[0], system.n
    present = ~np.isnan(z)
    # the distinct patterns of present rows, and each instant's
    patterns, which = np.unique(present, axis=0, return_inverse=True)
    which = which.ravel()
    rows = [np.flatnonzero(p) for p in patterns]
    Hp = [H_all[r] for r in rows]
    HpT = [h.T.copy() for h in Hp]
    one_R = R.shape[1] == 1
    Rp = [R[:, 0][:, r[:, None], r] if one_R else None for r in rows]
    # [0 | z_k] of the rows present, and [F' 0; 0 1], [Q | 0] of each interval
    Z = []
    for k in range(K1):
        r = rows[which[k]]
        Zk = np.zeros((len(r), n + 1))
        Zk[:, n] = z[k, r]
        Z.append(Zk)
    FT = []
    for k in range(1, K1):
        Fk = np.eye(n + 1)
        Fk[:n, :n] = system.F_at(k).T
        FT.append(Fk)
    Fs = [None] + [f[:n, :n].T.copy() for f in FT]
    FT = [None, *FT]
    Qa = np.zeros((Q.shape[0], Q.shape[1], n, n + 1))
    Qa[..., :n] = Q
    W = np.empty((C, n, n + 1))
    W[..., :n] = P0
    W[..., n] = system.prior.mean
    mm, solve = np.matmul, np.linalg.solve
    kept: dict[int, list[tuple[np.ndarray, ...]]] = {}  # (S_k, V_k, X_k) by row count
    logdet, bad = np.zeros(C), np.zeros(C, dtype=bool)
    quad = np.zeros(C)
    for k in range(K1):
        if k % FLUSH == 0:
            quad += _factorise(kept, cholesky, logdet, bad)
        if k:
            W = mm(mm(Fs[k], W), FT[k])
            W += Qa[:, q_at[k - 1]]
        p = which[k]
        r = rows[p]
        if not len(r):
            continue
        V = mm(Hp[p], W)  # [H P | H x]
        V -= Z[k]  # [H P | -nu]
        HP = V[..., :n]
        S = mm(HP, HpT[p])
        S += Rp[p] if one_R else R[:, r_at[k]][:, r[:, None], r]
        X = solve(S, V)  # S^-1 [H P | -nu]: the gain K' and the whitened innovation
        kept.setdefault(len(r), []).append((S, V[..., n], X[..., n]))
        W = W - mm(HP.swapaxes(-1, -2), X)  # [P - K H P | x + K nu]
        P = W[..., :n]
        P += P.swapaxes(-1, -2).copy()
        P *= 0.5
    quad += _factorise(kept, cholesky, logdet, bad)
    ll = -0.5 * (quad + logdet + LOG_2PI * int(present.sum()))
    ll[bad | ~np.isfinite(ll)] = -np.inf
    return ll


def _factorise(kept: dict[int, list[tuple[np.ndarray, ...]]], cholesky, logdet, bad):
    """Add log det S of the kept S_k (C, d, d) to `logdet` (C,), mark in `bad` the candidates
    with one that is not positive definite (one factorisation per row count d), and return
    the kept quadratic forms nu' S^-1 nu summed (C,)."""
    quad = 0.0
    for items in kept.values():
        S, v, w = (np.stack(a, axis=1) for a in zip(*items, strict=True))  # (C, T, ...)
        L, failed = cholesky(0.5 * (S + S.swapaxes(-1, -2)))
        bad |= failed
        logdet += 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=(1, 2))
        quad = quad + np.einsum("ctr,ctr->c", v, w)
    kept.clear()
    return quad
