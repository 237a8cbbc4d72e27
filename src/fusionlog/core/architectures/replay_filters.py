"""The sequential recursions of a single replayed log (`replay`): every Kalman filter of every
architecture stepped together, instant by instant, with a fixed number of numpy calls per
instant whatever the number of filters.

A plan (`filters.KalmanStack`) computes, at every step, the maps the exact analysis and the
per-run path need (T, U, O, the error propagation) for each architecture on its own. One run
without an exact analysis needs only the covariances and gains: here the centralised KF, the
per-sensor local filters (shared by MSC, MSC-GMF, CI, AVG and SKF: they are the same filters)
and HKF's fused filter with its local updates are one batch of *slots* predicted and updated
by the same few calls, each slot with the rows of z_k it uses (`masked`: an absent row of H is
zero and its component decoupled with unit variance, so its gain column is exactly zero and a
slot without data keeps its prediction, to the bit). The formulas are those of the plans:
prediction sym(F P F' + G Q G'), gain P H' (H P H' + R)^-1 of eq. (17) and the Joseph form of
eq. (18) (`kalman.gain`, `kalman.joseph`), HKF's fusion eqs. (36)-(40). What does not feed back
into a recursion (the means, the fusion rules, the smoother's fusion) is computed afterwards
for all instants at once (`replay`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..linalg import solve


def _solve(A: np.ndarray, B: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """np.linalg.solve, into `out` if given (raises LinAlgError where A is singular: `replay`
    then hands the log to the plans, which name the failing step)."""
    X = np.linalg.solve(A, B)
    if out is None:
        return X
    out[...] = X
    return out


_inv = np.linalg.inv


@dataclass
class Slots:
    """The filters stepped together: slot b uses the components `use[b]` of z_k and starts
    every step from the covariance `carried[src[b]]`; `hkf` is the first of HKF's slots (its
    fused prediction alone, then one local update per sensor), None without HKF."""

    use: np.ndarray  # (B, m) bool
    src: np.ndarray  # (B,) int
    carried: int
    hkf: int | None


@dataclass
class Bank:
    """What the slots' recursion gives at every instant: each slot's updated covariance, gain
    (columns in z_k's order, zero for unused components) and I - K H; HKF's fused covariance
    (in its first slot's place) and the informations [P_pred^-1, P_1^-1, ..., P_S^-1] of
    eqs. (36)-(38)."""

    P: np.ndarray  # (K+1, B, n, n)
    K: np.ndarray  # (K+1, B, n, m)
    IKH: np.ndarray  # (K+1, B, n, n)
    P_hkf: np.ndarray | None  # (K+1, n, n)
    Y_hkf: np.ndarray | None  # (K+1, S+1, n, n)


def masked_rows(H: np.ndarray, R: np.ndarray, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`filters.masked` for every instant and slot at once: H (m, n), R (K+1, m, m), present
    (K+1, B, m) -> H (K+1, B, m, n), R (K+1, B, m, m)."""
    pf = present.astype(float)
    Hm = H * pf[..., :, None]
    Rm = R[:, None] * (pf[..., :, None] * pf[..., None, :])
    Rm += np.eye(H.shape[0]) * (1.0 - pf)[..., None, :]
    return Hm, Rm


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + A.swapaxes(-1, -2))


def run_bank(
    slots: Slots,
    P0: np.ndarray,
    Fs: np.ndarray,
    Qs: np.ndarray,
    Hm: np.ndarray,
    Rm: np.ndarray,
    predict_first: bool = False,
) -> Bank:
    """Step every slot through the instants: Fs, Qs (K, n, n) the transition and process noise
    into instants 1..K, Hm, Rm (K+1, B, m, .) each slot's masked H and R (`masked_rows`).
    `predict_first` (a block of time after the first, `replay_blocks`): P0 is each carried
    covariance (C, n, n) of the instant before, and Fs, Qs (K+1, n, n) go into every instant.

    Per instant a fixed number of numpy calls on the whole batch of slots, results written
    into the arrays kept (`out=`); the products and sums in the plans' order, so that a slot
    gets the plans' numbers (to the last bit where LAPACK and BLAS take the same paths)."""
    K1, B, m, n = Hm.shape
    C, src, h = slots.carried, slots.src, slots.hkf
    S = B - h - 1 if h is not None else 0
    mm, add = np.matmul, np.add
    eye = np.eye(n)
    P_out = np.empty((K1, B, n, n))
    KT_out = np.empty((K1, B, m, n))
    IKH_out = np.empty((K1, B, n, n))
    Yh_out = np.empty((K1, S + 1, n, n)) if h is not None else None
    # per-instant views made once: indexing a list costs less than indexing an array
    Hs, HTs, Rs = list(Hm), list(Hm.swapaxes(-1, -2)), list(Rm)
    pad = [] if predict_first else [None]
    Fl, FTl, Ql = [*pad, *Fs], [*pad, *Fs.swapaxes(-1, -2)], [*pad, *Qs]
    Pl, KTl, IKHl = list(P_out), list(KT_out), list(IKH_out)
    Yhl = list(Yh_out) if h is not None else None
    identity = bool((src == np.arange(B)).all())
    KH = np.empty((B, n, n))
    Pc = np.array(np.broadcast_to(P0, (C, n, n)))
    for k in range(K1):
        if k or predict_first:  # prediction sym(F P F' + G Q G')
            A = mm(mm(Fl[k], Pc), FTl[k])
            A += Ql[k]
            Pp = A + A.swapaxes(-1, -2)
            Pp *= 0.5
        else:
            Pp = Pc
        Pb = Pp if identity else Pp[src]
        H, R = Hs[k], Rs[k]
        # gain K = P H' sym(H P H' + R)^-1, eq. (17) as `kalman.gain`
        HP = mm(H, Pb)
        Sk = mm(HP, HTs[k])
        Sk += R
        Ss = Sk + Sk.swapaxes(-1, -2)
        Ss *= 0.5
        X = _solve(Ss, HP, out=KTl[k])  # K', kept
        K, IKH, P = X.swapaxes(-1, -2), IKHl[k], Pl[k]
        mm(K, H, out=KH)
        np.subtract(eye, KH, out=IKH)
        # Joseph form, eq. (18) as `kalman.joseph`
        A = mm(mm(IKH, Pb), IKH.swapaxes(-1, -2))
        A += mm(mm(K, R), X)
        add(A, A.swapaxes(-1, -2), out=P)
        P *= 0.5
        if h is None:
            Pc = P
            continue
        # HKF, eqs. (36)-(38): Y_pred and Y_j (the slot h keeps the prediction, exactly),
        # Y = (1 - S) Y_pred + Y_1 + ... + Y_S, and the fused P = Y^-1 in slot h's place
        Yi = _inv(P[h:])
        Y = Yhl[k]
        add(Yi, Yi.swapaxes(-1, -2), out=Y)
        Y *= 0.5
        Yf = Y[0] * (1.0 - S)
        for j in range(1, S + 1):
            Yf += Y[j]
        Pi = _inv(Yf)
        Ph = P[h]
        add(Pi, Pi.T, out=Ph)
        Ph *= 0.5
        Pc = P[: h + 1]
    Ph_out = P_out[:, h] if h is not None else None
    return Bank(P_out, KT_out.swapaxes(-1, -2), IKH_out, Ph_out, Yh_out)


def affine_recursion(A: np.ndarray, b: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """x_k = A_k x_{k-1} + b_k for k = 0..K from x_{-1} = x0, for a stack of recursions:
    A (K+1, f, n, n), b (K+1, f, n), x0 (f, n) -> x (K+1, f, n)."""
    K1, f, n = b.shape
    out = np.empty((K1, f, n, 1))
    x = x0[..., None]
    bb = b[..., None]
    for k in range(K1):
        x = out[k] = A[k] @ x + bb[k]
    return out[..., 0]


def joint_recursion(A: np.ndarray, C: np.ndarray, J0: np.ndarray) -> np.ndarray:
    """The local filters' joint error covariance of eq. (35), J_k = sym(A_k J_{k-1} A_k' + C_k)
    from J_{-1} = J0, with A_k = Psi_k Phi_k and C_k = Psi_k Gam Q_k Gam' Psi_k' + Lam_k R_k
    Lam_k' (`replay` forms them for all instants at once): (K+1, S n, S n)."""
    out = np.empty(C.shape)
    J = J0
    AT = A.swapaxes(-1, -2)
    for k in range(len(C)):
        J = out[k] = _sym(A[k] @ J @ AT[k] + C[k])
    return out


def information(Hm: np.ndarray, Rm: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The information a reading adds, eq. (25): W = H' R^-1 H (K+1, n, n) and c = H' R^-1 z
    (K+1, n), from the masked H, R (K+1, m, .) of `masked_rows` and z (K+1, m) (0 where
    absent: a masked row adds nothing)."""
    RiH = solve(Rm, Hm, hermitian=True)  # (K+1, m, n): R^-1 H
    return Hm.swapaxes(-1, -2) @ RiH, np.einsum("kmi,km->ki", RiH, z)


def backward_information(
    W: np.ndarray, Fs: np.ndarray, Qs: np.ndarray, S_end: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """FBS's backward information filter, eqs. (25)-(28) as `fbs.build_fbs`: S_K = 0 and for
    k = K-1..0, S^+ = sym(S_{k+1} + H' R^-1 H at k+1) (W, (K+1, n, n)), L_k = F' (I + S^+ G Q
    G')^-1 (F, G Q G' into instant k+1), S_k = sym(L_k S^+ F). Returns L (K, n, n) and S
    (K+1, n, n). `S_end`: S_K where the instants end before the log's end (a block of time,
    `replay_blocks`: the S of the block after's first instant), else 0."""
    K1, n = W.shape[0], W.shape[-1]
    eye = np.eye(n)
    L = np.empty((K1 - 1, n, n))
    Smat = np.empty((K1, n, n))
    Smat[-1] = 0.0 if S_end is None else S_end
    Sk = Smat[-1]
    for k in range(K1 - 2, -1, -1):
        Splus = _sym(Sk + W[k + 1])
        F = Fs[k]
        Bm = eye + Splus @ Qs[k]
        Lk = L[k] = _solve(Bm.T, F).T
        Sk = Smat[k] = _sym(Lk @ Splus @ F)
    return L, Smat


def backward_means(L: np.ndarray, c: np.ndarray, y_end: np.ndarray | None = None) -> np.ndarray:
    """The backward information vectors y_K = 0 (`y_end` where the instants end before the
    log's end), y_k = L_k (y_{k+1} + c_{k+1}) with c_k = V_k z_k (K+1, n): (K+1, n)."""
    K1, n = c.shape
    out = np.zeros((K1, n, 1))
    if y_end is not None:
        out[-1, :, 0] = y_end
    cc = c[..., None]
    y = out[-1]
    for k in range(K1 - 2, -1, -1):
        y = out[k] = L[k] @ (y + cc[k + 1])
    return out[..., 0]
