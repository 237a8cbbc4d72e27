"""The sequential recursions of a single replayed log (`replay`): every Kalman filter of every
architecture stepped together, instant by instant, in one compiled loop (`replay_kernels`:
numpy calls on a batch of small matrices cost ~20 calls of microseconds per instant, which a
log of 10^6 instants cannot pay).

A plan (`filters.KalmanStack`) computes, at every step, the maps the exact analysis and the
per-run path need (T, U, O, the error propagation) for each architecture on its own. One run
without an exact analysis needs only the covariances and gains: here the centralised KF, the
per-sensor local filters (shared by MSC, MSC-GMF, CI, AVG and SKF: they are the same filters)
and HKF's fused filter with its local updates are one batch of *slots* predicted and updated
by the same loop, each slot with the rows of z_k it uses (`masked`: an absent row of H is
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


def _kernels():
    """The compiled loops (`replay_kernels`), imported where first used: importing numba
    costs ~0.5 s, which a command that replays nothing does not pay."""
    from . import replay_kernels

    return replay_kernels


def _arg(a: np.ndarray) -> np.ndarray:
    """a as the kernels take it: float64, C-ordered, writable (one compiled variant each)."""
    return np.require(a, dtype=float, requirements=["C", "W"])


def _singular(k: int, what: str) -> None:
    """numpy's error for a singular matrix at instant k (`replay` then hands the log to the
    plans, which name the failing step)."""
    if k >= 0:
        raise np.linalg.LinAlgError(f"singular matrix ({what}) at instant {k}")


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

    One compiled loop over the instants (`replay_kernels.bank`), the plans' formulas in their
    order: a slot gets the plans' numbers to rounding (their BLAS sums in another order)."""
    K1, B, m, n = Hm.shape
    C, h = slots.carried, slots.hkf
    S = B - h - 1 if h is not None else 0
    P_out = np.empty((K1, B, n, n))
    KT_out = np.empty((K1, B, m, n))
    IKH_out = np.empty((K1, B, n, n))
    Yh_out = np.empty((K1, S + 1, n, n))
    P0 = _arg(np.broadcast_to(P0, (C, n, n)))
    at = _kernels().bank(
        slots.src.astype(np.int64), -1 if h is None else h, P0, _arg(Fs), _arg(Qs),
        0 if predict_first else 1, _arg(Hm), _arg(Rm), P_out, KT_out, IKH_out, Yh_out,
    )  # fmt: skip
    _singular(at, "an innovation covariance or an information matrix")
    Ph_out = P_out[:, h] if h is not None else None
    return Bank(P_out, KT_out.swapaxes(-1, -2), IKH_out, Ph_out, Yh_out if h is not None else None)


def affine_recursion(A: np.ndarray, b: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """x_k = A_k x_{k-1} + b_k for k = 0..K from x_{-1} = x0, for a stack of recursions:
    A (K+1, f, n, n), b (K+1, f, n), x0 (f, n) -> x (K+1, f, n)."""
    out = np.empty(b.shape)
    _kernels().affine(_arg(A), _arg(b), _arg(x0), out)
    return out


def joint_recursion(A: np.ndarray, C: np.ndarray, J0: np.ndarray) -> np.ndarray:
    """The local filters' joint error covariance of eq. (35), J_k = sym(A_k J_{k-1} A_k' + C_k)
    from J_{-1} = J0, with A_k = Psi_k Phi_k and C_k = Psi_k Gam Q_k Gam' Psi_k' + Lam_k R_k
    Lam_k' (`replay` forms them for all instants at once): (K+1, S n, S n)."""
    out = np.empty(C.shape)
    _kernels().joint(_arg(A), _arg(C), _arg(J0), out)
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
    L = np.empty((K1 - 1, n, n))
    Smat = np.empty((K1, n, n))
    Smat[-1] = 0.0 if S_end is None else S_end
    _singular(_kernels().backward(_arg(W), _arg(Fs), _arg(Qs), L, Smat), "I + S G Q G'")
    return L, Smat


def backward_means(L: np.ndarray, c: np.ndarray, y_end: np.ndarray | None = None) -> np.ndarray:
    """The backward information vectors y_K = 0 (`y_end` where the instants end before the
    log's end), y_k = L_k (y_{k+1} + c_{k+1}) with c_k = V_k z_k (K+1, n): (K+1, n)."""
    out = np.zeros(c.shape)
    if y_end is not None:
        out[-1] = y_end
    _kernels().backward_vectors(_arg(L), _arg(c), out)
    return out
