"""The exact analysis of one long log in blocks of time when the truth is not the filters' model
(issue 34: `estimate --model`, a scenario's `[truth]` other than its prior, a truth with other
noise or dynamics), for logs without steady plans (irregular instants, per-message R, missing
readings).

The whole log's route is the plans' analysis (`exact.analyse`, `moments.step_moments`): the
joint moments of Z_k = [x_k; zeta_k], zeta_k = s_k - D x_k the estimator state's deviation,
propagated through each step's maps. Here the same moments are propagated without plans, from
the filters the plan-free replay carries block to block (`replay_blocks.ReplayBlocks`): each
group of filters is an affine map of its last state and the readings,

    s_k = T_k s_{k-1} + U_k z_k,    z_k = H_t x_k + v_k,    x_k = F_t x_{k-1} + w_k,

with T = (I - K H) F, U = K for the centralised KF (CKF, FBS's forward filter) and for the
stack of per-sensor local KFs (T block-diagonal), T = M F, U = B for HKF (eqs. 38-40), D the
stacked identities. So, with G_k = U_k H_t - D,

    zeta_k = T_k zeta_{k-1} + (T_k D + G_k F_t) x_{k-1} + G_k w_k + U_k v_k,

so A_k = [[F_t, 0], [T D + G F_t, T]], noise [I; G] w + [0; U] v (x left out where the
filters have the true F and H, `moments.coupling`: then A = T), the covariances by
`replay_filters.joint_recursion` and the means by `affine_recursion` (compiled), carried from
block to block. Each architecture's error is then e = (I - O D) x - O zeta (O its readout: the
identity for a filter, the fusion rule's weights for the per-sensor architectures), and for the
smoother (FBS, eqs. 25-28) e = (K_s - P_s B_k) x - (I - K_s) zeta_f - P_s eta_k, where the
backward information vector is y_b,k = B_k x_k + eta_k with B_k and cov(eta_k) from the backward
recursion of `exact._analyse`, run here from the log's end block by block first (`backward`;
the caller spools each instant's S, B and cov(eta) and hands them back to `window`).

Same formulas as the plans', not the same order of operations: the two agree to rounding.
Late sensors' stacked filters take the same definitions on the stacked model, x_k's error its
first `keep` rows (`core.latency_mismatch`).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from .architectures.replay_blocks import ReplayBlocks, system_window
from .architectures.replay_filters import (
    affine_recursion,
    backward_information,
    joint_recursion,
    masked_rows,
)
from .exact import Expected, shared_nees_and_dm
from .linalg import mT, solve, sym
from .model import System
from .moments import coupling

__all__ = ["CHUNK", "MismatchBlocks", "mismatch_blocks"]

#: Instants whose joint maps (A_k, the noise's C_k: (N, N) each, N up to (S + 1) n) are formed
#: at once inside a block of time: a few megabytes whatever the block.
CHUNK = 4096


def _masked(R: np.ndarray, present: np.ndarray) -> np.ndarray:
    """R (w, m, m) with the absent components decoupled at unit variance (their gain columns
    are zero: any value would do, but a per-message R may be NaN there)."""
    pf = present.astype(float)
    R = np.where(pf[:, :, None] * pf[:, None, :] > 0, R, 0.0)
    return R + np.eye(pf.shape[1]) * (1 - pf)[:, None]


def _windows(sw: System, k0: int, k1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F, G Q G' into each instant k0..k1-1 (the log's instant 0: I and 0, no prediction) and
    R there (w, ...) of `sw`, a system on those instants (`system_window`'s)."""
    w, n = k1 - k0, sw.n
    p0 = 1 if k0 == 0 else 0
    Fs, Qs = sw.transitions(0, w - p0)
    if p0:
        Fs = np.concatenate([np.eye(n)[None], Fs])
        Qs = np.concatenate([np.zeros((1, n, n)), Qs])
    R = sw.Rs if sw.Rs is not None else np.broadcast_to(sw.R, (w, sw.m, sw.m))
    return Fs, Qs, R


class MismatchBlocks:
    """Each architecture's exact values on one run of `model`'s filters whose data come from
    `truth` (both on the log's instants, the truth's sensors in the filters' order), block of
    time by block, in order (`window`); FBS's backward recursion first, in reverse order
    (`backward`). `mismatch_blocks` says whether the path takes them (the caller:
    `exact_replay.replay_expected_blocks`)."""

    def __init__(
        self, model: System, truth: System, blocks: ReplayBlocks, coupled: bool | None = None
    ) -> None:
        self.model, self.truth, self.blocks = model, truth, blocks
        self.archs, self.steps = blocks.archs, blocks.steps
        self.n = n = model.n
        #: x stays in the joint (`coupling_of`, unless the caller knows: a stacked model's
        #: per-block F is not the one `model` holds, `core.latency_mismatch`)
        self.nx = n if (coupling_of(model, truth) if coupled is None else coupled) else 0
        self.Ht = truth.linear_measurement()
        #: the error's leading rows the values are of (a stacked model's: x_k's n)
        self.keep = n
        self.moments: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def smoother(self) -> bool:
        """FBS is among the architectures: `window` needs `backward`'s rows."""
        return self.blocks.smoother

    @property
    def width(self) -> int:
        """Doubles per instant of `backward`'s rows: S, B, cov(eta)."""
        return 3 * self.n * self.n

    # -- FBS's backward recursion ----------------------------------------------------------------

    def backward(
        self, k0: int, k1: int, present: np.ndarray, after: tuple | None
    ) -> tuple[np.ndarray, tuple]:
        """The instants k0..k1-1 (`present` (w, m) their readings; `after` what the block
        after returned, None for the log's last block): rows (w, 3 n^2) of the backward
        information filter's S (eqs. 25-28, as `ReplayBlocks.backward`) and, under the truth,
        B and cov(eta) of y_b = B x + eta (`exact._analyse`), and what the block before
        takes."""
        model, truth, n = self.model, self.truth, self.n
        w = k1 - k0
        last = after is None
        mw = system_window(model, k0, k1, False)
        R = mw.Rs if mw.Rs is not None else np.broadcast_to(mw.R, (w,) + mw.R.shape)
        Hm, Rmk = masked_rows(model.linear_measurement(), R, present[:, None, :])
        Hm, Rmk = Hm[:, 0], Rmk[:, 0]
        V = mT(solve(Rmk, Hm, hermitian=True))  # (w, n, m): H' R^-1, masked
        W = V @ Hm
        Rt = system_window(truth, k0, k1, False)
        Rt = Rt.Rs if Rt.Rs is not None else np.broadcast_to(Rt.R, (w,) + Rt.R.shape)
        Rt = _masked(Rt, present)
        end = k1 - 1 if last else k1
        Fs, Qs = model.transitions(k0, end)
        Ft, Qt = truth.transitions(k0, end)
        if last:
            L, Smat = backward_information(W, Fs, Qs)
            Vn, Rn, Bn, Cn = V[1:], Rt[1:], np.zeros((n, n)), np.zeros((n, n))
        else:
            S1, W1, V1, R1, Bn, Cn = after
            L, Smat = backward_information(np.concatenate([W, W1[None]]), Fs, Qs, S1)
            Smat = Smat[:w]
            Vn, Rn = np.concatenate([V[1:], V1[None]]), np.concatenate([Rt[1:], R1[None]])
        # instants k = k1-2 (or k1-1)..k0 from the one after, in reverse order for the kernels
        r = slice(None, None, -1)
        L, Vn, Rn, Ft, Qt = L[r], Vn[r], Rn[r], Ft[r], Qt[r]
        VH = Vn @ self.Ht
        if self.nx:  # B_k = L_k (B_{k+1} + V H_t) F_t, as vec(B) (row-major): (L (x) F_t') vec(B)
            A = np.einsum("kij,klm->kiljm", L, mT(Ft)).reshape(len(L), 1, n * n, n * n)
            b = (L @ VH @ Ft).reshape(len(L), 1, n * n)
            B = affine_recursion(A, b, Bn.reshape(1, n * n)).reshape(len(L), n, n)
            Bplus = np.concatenate([Bn[None], B[:-1]]) + VH
        else:  # the true F and H: B = S (the same recursion), B + V H = S^+
            B = Smat[:-1][r] if last else Smat[r]
            Bplus = np.concatenate([Bn[None], B[:-1]]) + VH
        noise = L @ (Bplus @ Qt @ mT(Bplus) + Vn @ Rn @ mT(Vn)) @ mT(L)
        Ceta = joint_recursion(L, sym(noise), Cn)
        B, Ceta = B[r], Ceta[r]
        if last:
            B = np.concatenate([B, np.zeros((1, n, n))])
            Ceta = np.concatenate([Ceta, np.zeros((1, n, n))])
        rows = np.concatenate([a.reshape(w, -1) for a in (Smat, B, Ceta)], axis=1)
        return rows, (Smat[0].copy(), W[0].copy(), V[0].copy(), Rt[0].copy(), B[0].copy(),
                      Ceta[0].copy())  # fmt: skip

    # -- the forward moments --------------------------------------------------------------------

    def _initial(self, s0: np.ndarray, filters: int) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of [x_0; zeta_-1] (x left out where it decouples), zeta_-1 =
        s0 - D x_0 for `filters` stacked means s0 (`moments.initial_moments`)."""
        n, init = self.n, self.truth.truth_initial
        D = np.tile(np.eye(n), (filters, 1))
        J = np.vstack([np.eye(n), -D])[n - self.nx :]
        mu = np.concatenate([init.mean, s0 - D @ init.mean])[n - self.nx :]
        return mu, J @ init.cov @ J.T

    def _propagate(self, group: str, T, U, Ft, Qt, Rt, filters: int):
        """The moments (w, N) and (w, N, N) of the group's Z_k at the block's instants from the
        carried ones (`moments.step_moments`' A, B_w, B_v), a chunk of instants at a time."""
        n, nx = self.n, self.nx
        if group not in self.moments:
            self.moments[group] = self._initial(np.tile(self.model.prior.mean, filters), filters)
        mu, C = self.moments[group]
        w, d = T.shape[0], T.shape[-1]
        D = np.tile(np.eye(n), (filters, 1))
        mus, Cs = np.empty((w, nx + d)), np.empty((w, nx + d, nx + d))
        for a in range(0, w, CHUNK):
            b = min(a + CHUNK, w)
            Tc, Uc, F, Q, R = T[a:b], U[a:b], Ft[a:b], Qt[a:b], Rt[a:b]
            G = Uc @ self.Ht - D
            noise = Uc @ R @ mT(Uc)
            if nx:
                A = np.zeros((b - a, nx + d, nx + d))
                A[:, :nx, :nx], A[:, nx:, nx:] = F, Tc
                A[:, nx:, :nx] = Tc @ D + G @ F
                Bw = np.concatenate([np.broadcast_to(np.eye(n), (b - a, n, n)), G], axis=1)
                C_noise = Bw @ Q @ mT(Bw)
                C_noise[:, nx:, nx:] += noise
            else:
                A, C_noise = Tc, noise + G @ Q @ mT(G)
            Cs[a:b] = joint_recursion(A, sym(C_noise), C)
            mus[a:b] = affine_recursion(A[:, None], np.zeros((b - a, 1, nx + d)), mu[None])[:, 0]
            mu, C = mus[b - 1], Cs[b - 1]
        self.moments[group] = (mu.copy(), C.copy())
        return mus, Cs

    def window(self, k0: int, k1: int, present: np.ndarray, backward=None) -> dict[str, Expected]:
        """Each architecture's `Expected` (w, ...) at the instants k0..k1-1, `present` (w, m)
        their readings, `backward` the rows `backward` gave there (FBS)."""
        z = np.where(present, 0.0, np.nan)
        Sb = None
        if backward is not None:
            n2 = self.n * self.n
            Sb = [backward[:, i * n2 : (i + 1) * n2].reshape(-1, self.n, self.n) for i in range(3)]
        hand = None if Sb is None else (np.zeros((k1 - k0, self.n)), Sb[0])
        return self.blocks._block(k0, k1, z, hand, lambda r: self._expected(r, k0, k1, Sb))

    def values(self, k0: int, k1: int, present: np.ndarray) -> dict[str, tuple]:
        """Each architecture's (MSE matrix, bias, reported covariance) (w, ...) at the instants
        k0..k1-1 (no smoother), `present` (w, m) their readings: `window` without the NEES and
        DM, for a caller that cuts its blocks finer than the values it reports."""
        z = np.where(present, 0.0, np.nan)
        return self.blocks._block(k0, k1, z, None, lambda r: self._values(r, k0, k1, None))

    def truth_window(self, k0: int, k1: int) -> System:
        """The truth on the instants k0..k1-1 (`system_window`, into k0 from the block
        before)."""
        return system_window(self.truth, k0, k1, k0 > 0)

    def _expected(self, r, k0: int, k1: int, Sb) -> dict[str, Expected]:
        """The block's values from its filters `r` (`replay._Replay`)."""
        out = {}
        for a, (mse, bias, P) in self._values(r, k0, k1, Sb).items():
            nees, dm, _ = shared_nees_and_dm(P, bias, mse)
            out[a] = Expected(mse, bias, P, nees, dm)
        return out

    def _values(self, r, k0: int, k1: int, Sb) -> dict[str, tuple]:
        """The block's (MSE, bias, P) of the error's first `keep` rows from its filters `r`."""
        n, nx, w = self.n, self.nx, k1 - k0
        b = r.bank
        Ft, Qt, Rt = _windows(self.truth_window(k0, k1), k0, k1)
        Rt = _masked(Rt, r.present)
        F = r.Fs if not r.p0 else np.concatenate([np.eye(n)[None], r.Fs])
        groups: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        need = self.blocks.need
        if r.ckf is not None:
            c = r.ckf
            groups["ckf"] = self._propagate("ckf", b.IKH[:, c] @ F, b.K[:, c], Ft, Qt, Rt, 1)
        if r.loc is not None:
            S, lo = r.S, r.loc
            T = np.zeros((w, S * n, S * n))
            for j in range(S):
                T[:, j * n : (j + 1) * n, j * n : (j + 1) * n] = b.IKH[:, lo + j] @ F
            U = b.K[:, lo : lo + S].reshape(w, S * n, -1)
            groups["loc"] = self._propagate("loc", T, U, Ft, Qt, Rt, S)
        if "hierarchical" in need:
            M, Bh = r._hkf_maps()
            groups["hkf"] = self._propagate("hkf", M @ F, Bh, Ft, Qt, Rt, 1)
        out = {}
        for a, (arch, sensor) in zip(self.archs, self.blocks.bases, strict=True):
            kind = arch.locals
            extra = None
            if kind == "centralised":
                (mu, C), O, P = groups["ckf"], np.eye(n), b.P[:, r.ckf]
                L = self._readout(O, 1, w)
            elif kind == "single":
                j = self.model.sensor_index(sensor)
                (mu, C), P = groups["loc"], b.P[:, r.loc + j]
                O = np.zeros((n, r.S * n))
                O[:, j * n : (j + 1) * n] = np.eye(n)
                L = self._readout(O, r.S, w)
            elif kind == "hierarchical":
                (mu, C), P = groups["hkf"], b.P_hkf
                L = self._readout(np.eye(n), 1, w)
            elif kind == "smoother":
                (mu, C) = groups["ckf"]
                Ks, P = r._smoothing
                A = np.eye(n) - Ks
                L = -A if not nx else np.concatenate([Ks - P @ Sb[1], -A], axis=-1)
                extra = (P, Sb[2])
            else:  # a fusion rule of the local filters
                (mu, C), (O, P) = groups["loc"], r._weights(arch)
                L = self._readout(O, r.S, w)
            L, P = L[:, : self.keep], P[:, : self.keep, : self.keep]
            bias = (L @ mu[..., None])[..., 0]
            mse = L @ C @ mT(L)
            if extra is not None:
                mse = mse + extra[0] @ extra[1] @ mT(extra[0])
            out[a] = (sym(mse) + bias[:, :, None] * bias[:, None, :], bias, P)
        return out

    def _readout(self, O: np.ndarray, filters: int, w: int) -> np.ndarray:
        """e = (I - O D) x - O zeta's row block L (w, n, N) (x left out where it decouples)."""
        O = np.broadcast_to(O, (w,) + O.shape[-2:])
        if not self.nx:
            return -O
        D = np.tile(np.eye(self.n), (filters, 1))
        return np.concatenate([np.eye(self.n) - O @ D, -O], axis=-1)


def coupling_of(model: System, truth: System) -> bool:
    """`moments.coupling` of the filters' model and the truth: whether x stays in the joint."""
    return coupling(SimpleNamespace(system=model), truth)


def mismatch_blocks(model: System, truth: System, blocks: ReplayBlocks) -> MismatchBlocks | None:
    """`MismatchBlocks` of the filters `blocks` (`ReplayBlocks.of` of `model`) on data from
    `truth`, where the truth is linear with the filters' sizes; else None."""
    if not truth.linear or truth.motion_model is not None:
        return None
    if truth.n != model.n or truth.m != model.m:
        return None
    return MismatchBlocks(model, truth, blocks)
