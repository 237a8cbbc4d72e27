"""Error covariances of the stacked model's filters where correlated readings of one instant
arrive apart (reprocess, neglect; `core.latency_corr.apart_pairs`), one run in blocks of time
(`core.latency_blocks`).

A filter on the stacked model X_k = [x_k; ...; x_{k-W}] (`latency_stacked.stacked_system`)
takes the reading of slot c = (sensor j, lag l, component o) at k as H x_{k-l} + v_{k-l}[o]:
its noise is the raw noise of instant k - l, white across instants with the joint R of that
instant (cross-sensor blocks included). Where sensor i's reading of instant t reaches a filter
at k1 and sensor j's, correlated with it, at k2 != k1, the stacked noise is correlated across
time, which the recursions of eq. (35) (the locals' joint J) and of HKF's error (eqs. 38-40)
-- white stacked noise -- do not see. As in `core.latency_joint` (the plans' route, the affine
maps on z as taken), the raw noises still to be read are kept in the state: with the stacked
noise v~_k = Sel [v_k; v_{k-1}; ...; v_{k-W}] (Sel picks slot c's v_{k-l}[o]) and an error
recursion e_k = A_k e_{k-1} + (process noise) - G_k v~_k,

    xi_k = [e_k; v_k; ...; v_{k-W+1}],
    xi_k = [[A_k, -G_k Sel_old], [0, shift]] xi_{k-1} + [-G_k Sel_new; I; 0] v_k + [w-term; 0],

Sel_new the columns of v_k, Sel_old those of v_{k-1}..v_{k-W}; cov(xi) follows the same
recursion as J (`replay_filters.joint_recursion`), its first block the error covariance. A
reading not taken or not accepted has a zero gain column, so the noises of absent readings,
kept with their R, never reach e. The covariance of xi at a block's last instant is what the
next block starts from (`Carried.J`, `Carried.E`).
"""

from __future__ import annotations

import numpy as np

from .architectures.replay import Carried, _Replay
from .architectures.replay_filters import joint_recursion

__all__ = ["ApartReplay", "selection"]


def selection(slots: np.ndarray, m: int, W: int) -> np.ndarray:
    """Sel (m~, (W+1) m): stacked slot c = (sensor, lag l, component o) reads v_{k-l}[o]."""
    out = np.zeros((len(slots), (W + 1) * m))
    out[np.arange(len(slots)), slots[:, 1] * m + slots[:, 2]] = 1.0
    return out


class ApartReplay(_Replay):
    """`replay._Replay` on the stacked model whose error recursions keep the raw noises not yet
    read (module docstring): `sel` (`selection`), `raw_R` (m, m) the joint R of one instant
    (or (K+1, m, m), each instant's: a recorded log's per-message covariances, v_k entering
    with R_k), `W` the window, set before the first error covariance is asked for."""

    sel: np.ndarray
    raw_R: np.ndarray
    W: int

    _aug_J: np.ndarray | None = None
    _aug_E: np.ndarray | None = None

    def _noise_carried(
        self, A: np.ndarray, Cw: np.ndarray, G: np.ndarray, start: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The error covariances (K+1, d, d) of e_k = A_k e_{k-1} + w-term (cov Cw) - G_k v~_k
        and cov(xi) at the last instant. `start`: cov(xi_{-1}) (D, D), or the first block's
        (d, d) error covariance (no readings before the log: its raw noises are zero)."""
        K1, d = A.shape[:2]
        m, W = self.raw_R.shape[-1], self.W
        D = d + W * m
        if start.shape[0] == d:  # before instant 0: no reading's noise yet
            start = np.pad(start, ((0, W * m), (0, W * m)))
        GS = G @ self.sel  # (K+1, d, (W+1) m): the loading on v_k, v_{k-1}, ..., v_{k-W}
        Aa = np.zeros((K1, D, D))
        Aa[:, :d, :d] = A
        Aa[:, :d, d:] = -GS[:, :, m:]
        Aa[:, d + m :, d : D - m] = np.eye((W - 1) * m)
        Bn = np.zeros((K1, D, m))
        Bn[:, :d] = -GS[:, :, :m]
        Bn[:, d : d + m] = np.eye(m)
        Ca = Bn @ self.raw_R @ Bn.swapaxes(-1, -2)
        Ca[:, :d, :d] += Cw
        cov = joint_recursion(Aa, Ca, start)
        return np.ascontiguousarray(cov[:, :d, :d]), cov[-1].copy()

    def _joint(self) -> np.ndarray:
        """J of the stacked locals (eq. 35 with the raw noises kept: module docstring)."""
        if self._J is not None:
            return self._J
        n, S, K1, p = self.n, self.S, self.K1, self.p0
        b, lo = self.bank, self.loc
        IKH = b.IKH[:, lo : lo + S]
        Lam = b.K[:, lo : lo + S].reshape(K1, S * n, -1)
        A = np.zeros((K1, S * n, S * n))
        PsiF = IKH.copy()
        PsiF[p:] = IKH[p:] @ self.Fs[:, None]
        for j in range(S):
            A[:, j * n : (j + 1) * n, j * n : (j + 1) * n] = PsiF[:, j]
        Cw = np.zeros((K1, S * n, S * n))
        PsiQ = (IKH[p:] @ self.Qs[:, None]).reshape(K1 - p, S * n, n)
        Cw[p:] = PsiQ @ IKH[p:].reshape(K1 - p, S * n, n).swapaxes(-1, -2)
        J0 = np.tile(self.system.prior.cov, (S, S)) if self.start is None else self.start.J
        self._J, self._aug_J = self._noise_carried(A, Cw, Lam, J0)
        return self._J

    def _hkf_error(self) -> np.ndarray:
        """HKF's error covariance (`replay._Replay._hkf_error`) with the raw noises kept."""
        M, B = self._hkf_maps()
        A, p = M.copy(), self.p0
        A[p:] = M[p:] @ self.Fs
        Cw = np.zeros_like(M)
        Cw[p:] = M[p:] @ self.Qs @ M[p:].swapaxes(-1, -2)
        E0 = self.system.prior.cov if self.start is None else self.start.E
        self._E, self._aug_E = self._noise_carried(A, Cw, B, E0)
        return self._E

    def carried(self) -> Carried:
        """`_Replay.carried` with cov(xi) in place of J and HKF's E."""
        out = super().carried()
        if self._aug_J is not None:
            out.J = self._aug_J
        if self._aug_E is not None:
            out.E = self._aug_E
        return out
