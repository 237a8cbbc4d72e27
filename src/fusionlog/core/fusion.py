"""Static fusion rules for N estimates of the same state (Ajgl-Simandl-Dunik, Sec. II; Gustafsson-
Hendeby, "The Sensor Fusion Formula").

Each rule returns the weighting matrices c_i of eq. (2) (so a caller can apply one set of weights to
many runs at once) and the covariance the rule claims for the fused estimate; `fuse` applies
weights.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from typing import Literal

import numpy as np

from .linalg import inv_or_nan, is_invertible, mT, spd_inv, sym


def fuse(weights: Sequence[np.ndarray], estimates: Sequence[np.ndarray]) -> np.ndarray:
    """x = sum_i c_i x_i, eq. (2); estimates may carry leading run dimensions (..., n)."""
    return sum(np.einsum("...ij,...j->...i", c, x) for c, x in zip(weights, estimates, strict=True))


def millman_weights(covs: Sequence[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Millman's formula for independent estimates, eqs. (10)-(11) and (32)-(34).

    P = (sum_j P_jj^-1)^-1, c_i = P P_ii^-1.
    """
    return ci_weights(covs, np.ones(len(covs)))


def bar_shalom_campo(
    P11: np.ndarray, P22: np.ndarray, P12: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray]:
    """Bar-Shalom-Campo combination of two correlated estimates, eqs. (8)-(9)."""
    P21 = mT(P12)
    D = P11 + P22 - P12 - P21
    # c2 = (P11 - P12) D^-1, computed as a solve with D^T = D.
    c2 = mT(np.linalg.solve(D, mT(P11 - P12)))
    c1 = np.eye(P11.shape[-1]) - c2
    P = P11 - c2 @ (P11 - P21)
    return [c1, c2], sym(P)


def gmf_weights(
    joint: np.ndarray, n: int, E: np.ndarray | None = None
) -> tuple[list[np.ndarray], np.ndarray]:
    """Generalised Millman formula, eqs. (2)-(7), in constrained least-squares form.

    Minimises J of eq. (5), tr(C Sigma C^T), subject to sum_i c_i = I (eq. 7), where Sigma is the
    (N n x N n) joint error covariance with blocks P_ij of eq. (1). The stationarity conditions are
    the KKT system  [Sigma E; E^T 0] [C^T; L] = [0; I]  with E = [I; ...; I]. Eq. (6) is this system
    with the multiplier eliminated; it needs Sigma - blocks to be invertible, which fails in the
    paper's own example (identical local filters sharing the prior). The KKT system is solved by
    least squares (pseudo-inverse), whose minimum-norm solution is optimal even when Sigma is
    singular: weights that differ by a null direction of Sigma give the same estimate almost surely.

    `E` generalises the constraint to sum_i c_i E_i = I for inputs s_i = E_i x + noise (an
    information vector has E_i = Y_i); weights that cannot meet it (too little information in
    all inputs together) come back as NaN. Returns the weights c_i and P of eq. (4).
    """
    C, P = gmf_weight_matrix(joint, n, E)
    N = joint.shape[-1] // n
    return [C[..., :, i * n : (i + 1) * n] for i in range(N)], P


@lru_cache(maxsize=32)
def _kkt_constants(N: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """E = [I; ...; I] (N n x n) of eq. (7) and the KKT right-hand side [0; I]."""
    rhs = np.zeros((N * n + n, n))
    rhs[N * n :] = np.eye(n)
    E = np.tile(np.eye(n), (N, 1))
    E.flags.writeable = rhs.flags.writeable = False  # shared by every call
    return E, rhs


def gmf_weight_matrix(
    joint: np.ndarray, n: int, E: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """`gmf_weights` with the weights side by side, C = [c_1 ... c_N] (..., n, N n): what a
    caller applying them to the stacked estimates uses directly. Returns C and P of eq. (4)."""
    N = joint.shape[-1] // n
    batch = joint.shape[:-2]
    general = E is not None
    E0, rhs = _kkt_constants(N, n)
    # Scale so that the KKT matrix mixes blocks of comparable size (R may span 1e-8 .. 1e8).
    scale = np.abs(joint.diagonal(0, -2, -1)).max(axis=-1)[..., None, None]
    scale = np.where(scale > 0, scale, 1.0)
    if general:
        E = np.broadcast_to(E, batch + (N * n, n))
        e_scale = np.abs(E).max(axis=(-2, -1))[..., None, None]
        e_scale = np.where(e_scale > 0, e_scale, 1.0)
        Es = E / e_scale
    else:  # E = [I; ...; I] needs no scaling
        Es = E0
    kkt = np.zeros(batch + (N * n + n, N * n + n))
    kkt[..., : N * n, : N * n] = joint / scale
    kkt[..., : N * n, N * n :] = Es
    kkt[..., N * n :, : N * n] = mT(Es)
    if kkt.ndim == 2:
        sol = np.linalg.lstsq(kkt, rhs, rcond=1e-12)[0]  # SVD-based minimum-norm solution
    else:  # lstsq does not batch; the pseudo-inverse gives the same minimum-norm solution
        sol = np.linalg.pinv(kkt, rcond=1e-12, hermitian=True) @ rhs
    Ct = sol[..., : N * n, :]  # (N n, n): stacked c_i^T
    if general:
        Ct = Ct / e_scale  # back to the unscaled E
    C = mT(Ct)
    if general:
        ok = np.max(np.abs(C @ E - np.eye(n)), axis=(-2, -1)) < 1e-8
        C = np.where(ok[..., None, None], C, np.nan)
    P = sym(C @ joint @ mT(C))
    return C, P


Criterion = Literal["trace", "det"]

#: Newton iterations at most per covariance-intersection problem (3 to 12 are typical; an
#: optimum with a weight of 1e-10 or less, far from the start 1/N, can take more).
CI_MAXITER = 100
#: A face of the simplex is solved when the cost's gradient varies over its inputs by at most
#: _CI_TOL times the cost scale (the cost is then within that of the face's optimum, by
#: convexity), or when the Newton decrement is below _CI_DEC times it: the cost is then within
#: half of that, and the last Newton step, if shorter than _CI_POLISH, is taken without a line
#: search (whose costs would differ by rounding only), for an omega accurate to about the
#: square of that step. An input left out comes back when moving weight to it lowers the
#: cost faster than _CI_TOL times the scale.
_CI_TOL = 1e-13
_CI_DEC = 1e-14
_CI_POLISH = 1e-5
#: Armijo's sufficient decrease, and the decrement below which a failed line search means
#: that the costs compared are equal up to rounding (converged) rather than a bad step.
_CI_ARMIJO = 1e-4
_CI_FLAT = 1e-13
#: A step that puts a weight at 0 is taken even if the cost rises by this much (relative to
#: the scale): a weight left at rounding level beside the optimum's vertex (1e-16) would
#: otherwise stall the line search, whose costs then differ only by rounding.
_CI_ROUND = 1e-14
#: Smallest pivot of the Newton system, relative to its diagonal entry (modified LDL^T).
_CI_PIVOT = 1e-10
#: An input alone replaces the optimiser's answer only if its cost is lower by this much
#: (relative for tr P, absolute for log det P).
_CI_END = 1e-9


def _rowsum(x: np.ndarray) -> np.ndarray:
    """x[:, 0] + x[:, 1] + ... in that order, (B, N) -> (B,). Written out rather than
    x.sum(axis=1): numpy may reduce a small axis in a different order depending on the other
    axes' sizes, which would make a problem's rounding depend on how many share the batch."""
    s = x[:, 0]
    for i in range(1, x.shape[1]):
        s = s + x[:, i]
    return s


def _diagsum(X: np.ndarray) -> np.ndarray:
    """Trace over the last two axes, added in index order (see `_rowsum`)."""
    s = X[..., 0, 0]
    for a in range(1, X.shape[-1]):
        s = s + X[..., a, a]
    return s


class _Info2:
    """Costs of CI problems with n = 2 as rational functions of omega.

    With Ybar the mean of the informations and D_i = Y_i - Ybar, Y(w) = Ybar + sum_i w_i D_i on
    the simplex, and for 2 x 2 matrices det(Ybar + E) = det Ybar + tr(adj(Ybar) E) + det E, so

        q(w) = det Y(w) = q0 + l^T w + w^T Q w,   t(w) = tr Y(w) = t0 + s^T w,

    l_i = tr(adj(Ybar) D_i), s_i = tr D_i, Q_ij = (D_i,11 D_j,22 + D_j,11 D_i,22)/2 - D_i,12 D_j,12,
    and tr P = t/q, log det P = -log q, with P = Y(w)^-1 = adj(Y(w))/q. Built once per problem,
    a cost, its gradient and Hessian then take O(N^2) operations, whatever the iteration.
    Centring on Ybar keeps differences between nearly equal inputs (two local filters whose
    histories differ many steps back) exact: every coefficient scales with D, so the gradient
    and curvature along the simplex come out to relative, not absolute, rounding.

    Keys compared: tr P for "trace" (lower is better, inf where Y(w) is not positive definite)
    and q = det Y(w) for "det" (higher is better, <= 0 there): no logarithm is needed to
    compare, so no transcendental function (whose SIMD and scalar versions may differ in the
    last bit) enters a decision.
    """

    n = 2

    def __init__(self, trace: bool, q0, t0, lin, s, Q) -> None:
        self.trace, self.q0, self.t0, self.lin, self.s, self.Q = trace, q0, t0, lin, s, Q

    @classmethod
    def of(cls, a: np.ndarray, b: np.ndarray, c: np.ndarray, trace: bool) -> _Info2:
        """From the entries [[a_i, b_i], [b_i, c_i]] of the informations, each (B, N)."""
        N = a.shape[1]
        am, bm, cm = _rowsum(a) / N, _rowsum(b) / N, _rowsum(c) / N
        da, db, dc = a - am[:, None], b - bm[:, None], c - cm[:, None]
        Q = 0.5 * (da[:, :, None] * dc[:, None, :] + dc[:, :, None] * da[:, None, :])
        Q = Q - db[:, :, None] * db[:, None, :]
        lin = cm[:, None] * da + am[:, None] * dc - 2.0 * bm[:, None] * db
        return cls(trace, am * cm - bm * bm, am + cm, lin, da + dc, Q)

    def take(self, rows: np.ndarray) -> _Info2:
        return _Info2(
            self.trace, self.q0[rows], self.t0[rows], self.lin[rows], self.s[rows], self.Q[rows]
        )

    def _q(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Qw = self.Q[:, :, 0] * w[:, :1]
        for j in range(1, w.shape[1]):
            Qw = Qw + self.Q[:, :, j] * w[:, j : j + 1]
        return self.q0 + _rowsum(w * (self.lin + Qw)), Qw

    def value(self, w: np.ndarray) -> np.ndarray:
        q, _ = self._q(w)
        if not self.trace:
            return q
        return np.where(q > 0, (self.t0 + _rowsum(self.s * w)) / q, np.inf)

    def derivs(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Key, gradient and Hessian in omega. With v = grad q = l + 2 Q w:
        tr P: g = s/q - t v/q^2, H = (2 f (v v^T - q Q) - s v^T - v s^T)/q^2 (f = t/q);
        log det P: g = -v/q, H = (v v^T/q - 2 Q)/q."""
        q, Qw = self._q(w)
        v = self.lin + 2.0 * Qw
        iq = 1.0 / q
        vv = v[:, :, None] * v[:, None, :]
        if self.trace:
            f = (self.t0 + _rowsum(self.s * w)) * iq
            g = (self.s - f[:, None] * v) * iq[:, None]
            sv = self.s[:, :, None] * v[:, None, :]
            H = 2.0 * f[:, None, None] * (vv - q[:, None, None] * self.Q) - (sv + mT(sv))
            return np.where(q > 0, f, np.inf), g, H * (iq * iq)[:, None, None]
        return q, -v * iq[:, None], (vv * iq[:, None, None] - 2.0 * self.Q) * iq[:, None, None]

    def decreased(self, old: np.ndarray, new: np.ndarray, amount: np.ndarray) -> np.ndarray:
        """Whether the cost fell by `amount` (Armijo). For log det P = -log q this is
        log(q_new/q_old) >= amount, tested through log x >= 1 - 1/x."""
        if self.trace:
            return (new <= old - amount) & (new < old)
        return (new > 0) & (new - old >= amount * new) & (new > old)

    def close(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """Whether `new` costs at most rounding (`_CI_ROUND`) more than `old`."""
        if self.trace:
            return new <= old + _CI_ROUND * old
        return (new > 0) & (new >= old - _CI_ROUND * old)

    def better(self, new: np.ndarray, old: np.ndarray) -> np.ndarray:
        """Whether `new` costs less than `old` by more than rounding (`_CI_END`)."""
        if self.trace:
            return new < old - _CI_END * np.abs(old)
        return new > old * (1.0 + _CI_END)

    def scale(self, key: np.ndarray) -> np.ndarray:
        """The cost's scale, for relative tolerances: tr P itself; n for log det P (its
        gradient has sum_i w_i g_i = -n)."""
        return key.copy() if self.trace else np.full(key.shape, 2.0)


class _InfoN:
    """Costs of CI problems of any n with matrices: Y(w) = Ybar + sum_i w_i D_i (centred as in
    `_Info2`), P = Y(w)^-1 by LU, and with M_i = P D_i, C_i = M_i P:
    tr P: g_i = -tr C_i, H_ij = 2 tr(M_i C_j); log det P: g_i = -tr M_i, H_ij = tr(M_i M_j).
    Keys: tr P or -log det P (lower is better, inf where Y(w) is not positive definite). Every
    product is a matmul or LAPACK call per matrix, so each problem's numbers are its own."""

    def __init__(self, trace: bool, Ybar: np.ndarray, D: np.ndarray) -> None:
        self.trace, self.Ybar, self.D = trace, Ybar, D
        self.n = Ybar.shape[-1]

    @classmethod
    def of(cls, Ys: np.ndarray, trace: bool) -> _InfoN:
        Ybar = Ys[:, 0]
        for i in range(1, Ys.shape[1]):
            Ybar = Ybar + Ys[:, i]
        Ybar = Ybar / Ys.shape[1]
        return cls(trace, Ybar, Ys - Ybar[:, None])

    def take(self, rows: np.ndarray) -> _InfoN:
        return _InfoN(self.trace, self.Ybar[rows], self.D[rows])

    def _inv(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Y = self.Ybar
        for i in range(w.shape[1]):
            Y = Y + w[:, i, None, None] * self.D[:, i]
        sign, logdet = np.linalg.slogdet(Y)
        ok = sign > 0
        P = np.linalg.inv(np.where(ok[:, None, None], Y, np.eye(self.n)))
        return ok, logdet, P

    def value(self, w: np.ndarray) -> np.ndarray:
        ok, logdet, P = self._inv(w)
        return np.where(ok, _diagsum(P) if self.trace else -logdet, np.inf)

    def derivs(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ok, logdet, P = self._inv(w)
        B, N, n = self.D.shape[:3]
        M = P[:, None] @ self.D
        if self.trace:
            C = M @ P[:, None]
            f, g = _diagsum(P), -_diagsum(C)
            Ct = np.ascontiguousarray(mT(C)).reshape(B, N, n * n)
            H = 2.0 * (M.reshape(B, N, n * n) @ mT(Ct))
        else:
            f, g = -logdet, -_diagsum(M)
            Mt = np.ascontiguousarray(mT(M)).reshape(B, N, n * n)
            H = M.reshape(B, N, n * n) @ mT(Mt)
        return np.where(ok, f, np.inf), g, 0.5 * (H + mT(H))

    def decreased(self, old: np.ndarray, new: np.ndarray, amount: np.ndarray) -> np.ndarray:
        return (new <= old - amount) & (new < old)

    def close(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        return new <= old + _CI_ROUND * (np.abs(old) if self.trace else float(self.n))

    def better(self, new: np.ndarray, old: np.ndarray) -> np.ndarray:
        return new < old - _CI_END * (np.abs(old) if self.trace else 1.0)

    def scale(self, key: np.ndarray) -> np.ndarray:
        return key.copy() if self.trace else np.full(key.shape, float(self.n))


def _ldl_solve(K: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """K^-1 rhs for B small symmetric matrices K (B, N, N), by LDL^T written out over N (each
    operation runs over the problems), with each pivot raised to at least _CI_PIVOT times its
    diagonal entry: a modified Cholesky, so a direction of (nearly) zero curvature gives a long
    step, which the line search then cuts at the simplex's boundary, instead of a division by
    rounding noise or zero."""
    N = K.shape[-1]
    L: dict[tuple[int, int], np.ndarray] = {}
    Dinv: list[np.ndarray] = []
    LD: dict[tuple[int, int], np.ndarray] = {}  # L_jk D_k
    for j in range(N):
        d = K[:, j, j]
        for k in range(j):
            d = d - L[j, k] * LD[j, k]
        d = np.maximum(d, _CI_PIVOT * K[:, j, j])
        Dinv.append(1.0 / d)
        for i in range(j + 1, N):
            s = K[:, i, j]
            for k in range(j):
                s = s - L[i, k] * LD[j, k]
            LD[i, j] = s
            L[i, j] = s * Dinv[j]
    z: list[np.ndarray] = []
    for i in range(N):
        zi = rhs[:, i]
        for k in range(i):
            zi = zi - L[i, k] * z[k]
        z.append(zi)
    x: list[np.ndarray] = [np.empty(0)] * N
    for i in reversed(range(N)):
        xi = z[i] * Dinv[i]
        for k in range(i + 1, N):
            xi = xi - L[k, i] * x[k]
        x[i] = xi
    return np.stack(x, axis=1)


def _newton_direction(
    g: np.ndarray, H: np.ndarray, free: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Newton step on the face {w_i = 0 for i not free, sum w = 1} of B problems.

    The equality-constrained step minimises g^T d + d^T H d / 2 over d with d_i = 0 off the
    face and 1^T d = 0. With m the face's indicator and Pi = I - m m^T/|F| on it, that is
    d = -(Pi H Pi + sigma m m^T/|F|)^-1 Pi g: the added term only fixes the component along m
    (which Pi g does not have) and makes the matrix definite; the inputs off the face get the
    identity. Returns d, the decrement -g^T d = d^T H d, the mean of g over the face (minus
    the multiplier of 1^T w = 1) and the spread max_F g - min_F g.
    """
    B, N = g.shape
    m = free.astype(float)
    nf = _rowsum(m)
    gm = _rowsum(g * m) / nf
    gp = (g - gm[:, None]) * m
    r = H[:, :, 0] * m[:, :1]
    for j in range(1, N):
        r = r + H[:, :, j] * m[:, j : j + 1]
    r = r / nf[:, None]
    c = _rowsum(r * m) / nf
    mm = m[:, :, None] * m[:, None, :]
    Hp = (H - r[:, :, None] - r[:, None, :] + c[:, None, None]) * mm
    sigma = _diagsum(Hp) / np.maximum(nf - 1.0, 1.0)
    sigma = np.where(sigma > 1e-250, sigma, 1.0)
    K = Hp + (sigma / nf)[:, None, None] * mm
    K[:, np.arange(N), np.arange(N)] += 1.0 - m
    d = -_ldl_solve(K, gp) * m
    d = d - m * (_rowsum(d) / nf)[:, None]  # back onto 1^T d = 0 after rounding
    dec = -_rowsum(gp * d)
    spread = np.where(free, g, -np.inf).max(axis=1) - np.where(free, g, np.inf).min(axis=1)
    return d, dec, gm, spread


def _ci_newton(ev: _Info2 | _InfoN, w: np.ndarray, member: np.ndarray) -> np.ndarray:
    """Active-set Newton method for B CI problems from the start points w, each on its own.

    The free inputs F (a face of the simplex) start as `member`. Each iteration takes, for every
    unfinished problem, the Newton step on its face (`_newton_direction`), cut where a weight
    would turn negative, and backtracks (halving) until Armijo's decrease holds; a weight the
    cut step puts at 0 leaves F. A problem whose face is solved (see _CI_TOL, _CI_DEC) checks
    the KKT condition: for an input j outside F, the multiplier mu_j = g_j - mean_F g must be
    >= 0 (moving weight from F to j would not lower the cost); otherwise the most negative
    returns to F (once only if the next step would at once push it out again), else the
    problem is finished and leaves the batch. The costs are convex on the simplex, so this is
    the global optimum. Every test is per problem, and finished problems are frozen: a
    problem's iterates do not depend on the others in the batch.
    """
    B, N = w.shape
    out = w.copy()
    if not B:
        return out
    rows = np.arange(B)
    free = member.copy()
    key, g, H = ev.derivs(w)
    S = ev.scale(key)
    locked = np.zeros(B, bool)  # no more releases: one was undone at once
    stuck = np.zeros(B, bool)  # the line search ended at rounding level
    for _ in range(CI_MAXITER):
        at = np.arange(len(rows))
        d, dec, gm, spread = _newton_direction(g, H, free)
        # Not clearly above the tolerance also catches NaN (never from a finite problem).
        solved = ~(spread > _CI_TOL * S) | ~(dec > _CI_DEC * S) | stuck
        mu = np.where(member & ~free, g - gm[:, None], np.inf)
        j = np.argmin(mu, axis=1)
        release = solved & (mu[at, j] < -_CI_TOL * S) & ~locked
        free[at[release], j[release]] = True
        stuck &= ~release
        finished = solved & ~release
        # The last Newton step where the decrement (not the gradient's spread) ended it.
        polish = finished & (spread > _CI_TOL * S) & (dec <= _CI_DEC * S)
        polish &= (np.abs(d) <= _CI_POLISH).all(axis=1) & (w + d >= 0).all(axis=1)
        if polish.any():
            one = np.ones(polish.sum())
            w[polish] = _trial(w[polish], d[polish], one, one < 0, j[polish])  # (no cut)
        if finished.any():  # frozen: out of the batch
            out[rows[finished]] = w[finished]
            keep = ~finished
            if not keep.any():
                return out
            rows, w, free, member = rows[keep], w[keep], free[keep], member[keep]
            key, g, H, S = key[keep], g[keep], H[keep], S[keep]
            locked, stuck, solved = locked[keep], stuck[keep], solved[keep]
            d, dec = d[keep], dec[keep]
            ev = ev.take(keep)
            at = np.arange(len(rows))
        step = ~solved
        # The step, cut at the first weight to reach 0 (a returned input the step would push
        # out at once is left out again, for good).
        ratio = np.where(step[:, None] & free & (d < 0), w / np.where(d < 0, -d, 1.0), np.inf)
        jb = np.argmin(ratio, axis=1)
        amax = ratio[at, jb]
        again = step & (amax <= 0)
        free[at[again], jb[again]] = False
        locked |= again
        step &= ~again
        alpha = np.where(step, np.minimum(amax, 1.0), 0.0)
        blocked = step & (amax <= 1.0)
        wt = _trial(w, d, alpha, blocked, jb)
        kt, gt, Ht = ev.derivs(wt)
        ok = ev.decreased(key, kt, _CI_ARMIJO * alpha * dec)
        ok = step & (ok | (blocked & ev.close(key, kt)))
        bad = step & ~ok
        stuck |= bad & ~(dec > _CI_FLAT * S)
        back = np.flatnonzero(bad & (dec > _CI_FLAT * S))
        w[ok], key[ok], g[ok], H[ok] = wt[ok], kt[ok], gt[ok], Ht[ok]
        cut = ok & blocked
        free[at[cut], jb[cut]] = False
        if back.size:
            _backtrack(ev, back, w, d, alpha, dec, key, g, H, stuck)
    out[rows] = w  # the iteration limit (not reached in practice): the best point found
    return out


def _trial(
    w: np.ndarray, d: np.ndarray, alpha: np.ndarray, blocked: np.ndarray, jb: np.ndarray
) -> np.ndarray:
    """w + alpha d, the blocking weight set to exactly 0 and the sum back to 1."""
    wt = np.maximum(w + alpha[:, None] * d, 0.0)
    wt[np.flatnonzero(blocked), jb[blocked]] = 0.0
    return wt / _rowsum(wt)[:, None]


def _backtrack(ev, back, w, d, alpha, dec, key, g, H, stuck) -> None:
    """Halve the steps of the problems `back` until Armijo's decrease holds (updating w, key,
    g, H in place); after 60 halvings a problem counts as converged (`stuck`)."""
    sub = ev.take(back)
    a = alpha[back]
    none = np.zeros(len(back), bool)
    jb = np.zeros(len(back), int)
    for _ in range(60):
        a = 0.5 * a
        wt = _trial(w[back], d[back], a, none, jb)
        kt, gt, Ht = sub.derivs(wt)
        ok = ev.decreased(key[back], kt, _CI_ARMIJO * a * dec[back])
        hit = back[ok]
        w[hit], key[hit], g[hit], H[hit] = wt[ok], kt[ok], gt[ok], Ht[ok]
        back, a, none, jb = back[~ok], a[~ok], none[~ok], jb[~ok]
        if not back.size:
            return
        sub = sub.take(~ok)
    stuck[back] = True


def _invertible2(a: np.ndarray, b: np.ndarray, c: np.ndarray, rtol: float = 1e-13) -> np.ndarray:
    """`is_invertible` for symmetric 2 x 2 matrices [[a, b], [b, c]] without an eigensolver: for
    eigenvalues 0 <= x lam <= lam, det/tr^2 = x/(1 + x)^2 grows with x, so lam_min > rtol lam_max
    is det > rtol/(1 + rtol)^2 tr^2; the Jacobi-scaled matrix [[1, rho], [rho, 1]] has
    eigenvalues 1 -+ |rho|, so its test is rho^2 < ((1 - rtol)/(1 + rtol))^2, rho^2 = b^2/(a c)."""
    finite = np.isfinite(a) & np.isfinite(b) & np.isfinite(c)
    tr = a + c
    plain = (tr > 0) & (a * c - b * b > rtol / (1 + rtol) ** 2 * (tr * tr))
    pos = (a > 0) & (c > 0)
    scaled = pos & ((b / a) * (b / c) < ((1 - rtol) / (1 + rtol)) ** 2)
    return finite & (plain | scaled)


def _representatives(equal, B: int, N: int) -> np.ndarray:
    """rep (B, N): for each input the first input bit-for-bit equal to it (`equal(k, i)`, a
    boolean per problem)."""
    rep = np.empty((B, N), dtype=np.intp)
    for k in range(N):
        r = np.full(B, k)
        for i in reversed(range(k)):
            r[equal(k, i)] = i
        rep[:, k] = r
    return rep


def _ci_finish(ev: _Info2 | _InfoN, rep: np.ndarray) -> np.ndarray:
    """Newton from the merged start (each group of equal inputs as one, weight count/N), the
    end-point rule, and the weights split equally within each group."""
    B, N = rep.shape
    member = rep == np.arange(N)
    count = np.stack([_rowsum((rep == i).astype(float)) for i in range(N)], axis=1)
    w = _ci_newton(ev, np.where(member, count / N, 0.0), member)
    # End points: an input alone wins only if better by more than rounding.
    best = ev.value(w)
    for i in range(N):
        e = np.zeros((B, N))
        e[:, i] = 1.0
        win = member[:, i] & ev.better(ev.value(e), best)
        if win.any():
            w[win] = e[win]
            best = np.where(win, ev.value(w), best)
    return _split(w, rep)


def ci_omegas(infos: np.ndarray, criterion: Criterion = "trace") -> np.ndarray:
    """Covariance-intersection weights for many independent problems at once, on the simplex.

    infos (..., N, n, n): the inputs' information matrices Y_i = P_i^-1, any leading shape and
    strides (n = 2 reads them in place); the weights come back as (..., N). Each problem minimises
    tr P or log det P, P = (sum_i w_i Y_i)^-1, over w >= 0, sum_i w_i = 1. Both costs are convex
    in w (tr X^-1 and -log det X are convex on positive definite X), with
    d tr P/d w_i = -tr(P Y_i P), d^2 tr P/d w_i d w_j = 2 tr(P Y_i P Y_j P) and
    d log det P/d w_i = -tr(P Y_i), d^2 log det P/d w_i d w_j = tr(P Y_i P Y_j). They are solved
    all together by an active-set Newton method (`_ci_newton`: Newton steps on a face of the
    simplex, cut at its boundary, with Armijo backtracking and the KKT multipliers choosing the
    face), vectorised over the problems, from w = 1/N. For n = 2 (`_ci_omegas2`) exact tests
    at w = 1/N and at the end points, and closed forms on the edges, settle most problems
    without iterating, and the iteration itself needs no matrix algebra (`_Info2`); every
    answer passes the same optimality test. Every problem is solved on its own:
    the same problem gives the same omega to the last bit alone or among any others, so the
    shared path (one problem per step) and the per-run path (one per run and step) agree.

    Each problem's informations are first scaled to unit mean trace (omega does not change).
    Inputs whose informations are bit-for-bit equal are merged and share their weight equally.
    A singular input (a local filter that cannot see the whole state yet) makes the cost
    infinite on part of the simplex, which the line search never enters; a problem whose
    inputs together are singular has no CI estimate (NaN). The answer keeps w = 1/N when the
    cost's gradient there is the same for all inputs up to rounding (`_CI_TOL`; equal
    covariances: every omega gives the same P, and the interior answer also averages the
    estimates, where letting rounding pick an input would make the fused estimate jump from
    step to step); likewise an input alone (an end point) replaces the optimiser's answer only
    if better by more than rounding.
    """
    Ys = np.asarray(infos, dtype=float)
    lead, N, n = Ys.shape[:-3], Ys.shape[-3], Ys.shape[-1]
    if N == 1:
        return np.ones(lead + (1,))
    trace = criterion == "trace"
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if n == 2:
            return _ci_omegas2(Ys, trace)
        Ys = Ys.reshape((-1, N, n, n))
        B = len(Ys)
        total = Ys[:, 0]
        for i in range(1, N):
            total = total + Ys[:, i]
        tr = _diagsum(total) / (N * n)
        tr = np.where(tr > 0, tr, 1.0)
        out = np.full((B, N), np.nan)
        idx = np.flatnonzero(is_invertible(total / (N * tr)[:, None, None]))
        if idx.size:
            Ys = Ys[idx] / tr[idx, None, None, None]
            flat = Ys.reshape(len(idx), N, n * n)
            rep = _representatives(lambda k, i: (flat[:, k] == flat[:, i]).all(axis=1), len(idx), N)
            out[idx] = _ci_finish(_InfoN.of(Ys, trace), rep)
        return out.reshape(lead + (N,))


#: Problems per block of `_ci_omegas2`'s tests: the arrays of a block stay in the cache.
CI_BLOCK = 16384


def _ci_omegas2(Ys: np.ndarray, trace: bool) -> np.ndarray:
    """`ci_omegas` for n = 2, on the entries [[a_i, b_i], [b_i, c_i]] of the informations, each
    an array over the problems.

    Before any iteration, two exact optimality tests with the tolerances of `_ci_newton`:
    * at the start w = 1/N, with Ybar = mean Y_i = [[a, b], [b, c]], q = det Ybar, the gradient
      g_i = -tr(P Y_i P) is, up to a constant, -tr(D_i adj(Ybar)^2)/q^2 (D_i = Y_i - Ybar;
      for log det, -tr(D_i adj(Ybar))/q): if it varies by at most _CI_TOL times the cost,
      w = 1/N is the answer (equal inputs);
    * at an end point e_k (input k alone, P_k = Y_k^-1 = adj(Y_k)/q_k): the KKT multipliers
      mu_j = g_j - g_k = -tr((Y_j - Y_k) adj(Y_k)^2)/q_k^2 (for log det -tr((Y_j - Y_k)
      adj(Y_k))/q_k) are all >= -_CI_TOL times the cost scale: then e_k is the optimum (a
      local filter whose information dominates the others', the usual case in a bank of
      filters that differ only in which measurements they had). Used when the inputs that
      pass are all equal (one group, which then shares the weight).
    The other problems are gathered and tried on the edges (`_ci_edges2`, closed forms); those
    left go to `_ci_newton` with `_Info2`.
    """
    lead, N = Ys.shape[:-3], Ys.shape[-3]
    if not lead:
        return _ci_omegas2(Ys[None], trace)[0]
    # The output in the input's memory order, and both seen with the leading axes from the
    # outermost in memory to the innermost: blocks along the first of them then cover
    # contiguous memory, whatever layout the informations come in.
    out = np.empty_like(Ys[..., 0, 0])
    perm = sorted(range(len(lead)), key=lambda ax: -abs(Ys.strides[ax]))
    Yt = Ys.transpose(perm + [-3, -2, -1])
    ot = out.transpose(perm + [-1])
    shape = Yt.shape[:-3]
    k = 0  # split the first axis whose inner part fits a block
    while k < len(shape) - 1 and math.prod(shape[k + 1 :]) > CI_BLOCK:
        k += 1
    chunk = max(1, CI_BLOCK // math.prod(shape[k + 1 :]))
    rest: list[tuple[tuple, tuple]] = []
    for at in np.ndindex(shape[:k]):
        for r0 in range(0, shape[k], chunk):
            block = at + (slice(r0, r0 + chunk),)
            ot[block], left = _ci_tests2(Yt[block], trace)
            if left is not None:
                rest.append((block, left))
    if rest:
        sub = np.concatenate([Yt[block][left] for block, left in rest])
        tr = _diagsum(sub[:, 0])
        for i in range(1, N):
            tr = tr + _diagsum(sub[:, i])
        tr = tr / (2 * N)
        sub = sub / np.where(tr > 0, tr, 1.0)[:, None, None, None]
        a, c = sub[:, :, 0, 0], sub[:, :, 1, 1]
        b = 0.5 * (sub[:, :, 0, 1] + sub[:, :, 1, 0])
        rep = _representatives(lambda k, i: (sub[:, k] == sub[:, i]).all(axis=(1, 2)), len(sub), N)
        w = np.empty((len(sub), N))
        for r0 in range(0, len(sub), CI_BLOCK):  # blocks again, for the cache
            part = slice(r0, r0 + CI_BLOCK)
            w[part], done = _ci_edges2(a[part], b[part], c[part], rep[part], trace)
            if not done.all():
                todo = np.flatnonzero(~done)
                ev = _Info2.of(a[part][todo], b[part][todo], c[part][todo], trace)
                w[r0 + todo] = _ci_finish(ev, rep[part][todo])
        r0 = 0
        for block, left in rest:
            view = ot[block]
            view[left] = w[r0 : r0 + len(left[0])]
            r0 += len(left[0])
    return out


def _split(w: np.ndarray, rep: np.ndarray) -> np.ndarray:
    """Weights of the merged problems (on each group's first input) shared equally within each
    group of equal inputs."""
    B, N = rep.shape
    if (rep == np.arange(N)).all():
        return w
    count = np.stack([_rowsum((rep == i).astype(float)) for i in range(N)], axis=1)
    at = np.arange(B)[:, None]
    return w[at, rep] / count[at, rep]


def _ci_edges2(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, rep: np.ndarray, trace: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Optima on an edge of the simplex (two inputs), for n = 2, in closed form and certified.

    On the edge w = (1 - x) e_i + x e_j, Y = Y_i + x E (E = Y_j - Y_i) has
    det Y = c0 + c1 x + c2 x^2 (c0 = det Y_i, c1 = tr(adj(Y_i) E), c2 = det E) and
    tr Y = t0 + t1 x. tr P = (t0 + t1 x)/det Y has derivative -p(x)/det^2 with
    p(x) = t1 c2 x^2 + 2 t0 c2 x + (t0 c1 - t1 c0); the cost is convex, so its minimum is the
    root where p falls, x = (-b - sqrt(b^2 - 4 a c))/(2 a) in p's coefficients a, b, c,
    evaluated as 2 c/(sqrt(..) - b) when b < 0 (no cancellation either way). log det P =
    -log det Y has its minimum at x = -c1/(2 c2) when c2 < 0. A root inside (0, 1) is the
    answer if it passes the KKT test of `_ci_newton` at that point (with Y = Y(w) and
    Z = adj(Y)^2, or adj(Y) for log det: G_k = tr((Y_k - Y) Z) equal for i and j up to
    _CI_TOL, and no other input's G_k above theirs by more; g_k = const - G_k/q^2, or /q), and
    no other edge passes. Returns the weights (split within groups of equal inputs; garbage
    where not found) and where one was found.
    """
    B, N = a.shape
    member = rep == np.arange(N)
    A, Bq, C = a.T.copy(), b.T.copy(), c.T.copy()
    am, bm, cm = sum(A[1:], A[0]) / N, sum(Bq[1:], Bq[0]) / N, sum(C[1:], C[0]) / N
    S = (am + cm) / (am * cm - bm * bm) if trace else 2.0
    found = np.zeros(B)
    w = np.zeros((B, N))
    for i in range(N):
        for j in range(i + 1, N):
            Ea, Eb, Ec = A[j] - A[i], Bq[j] - Bq[i], C[j] - C[i]
            c1 = C[i] * Ea + A[i] * Ec - 2.0 * Bq[i] * Eb
            c2 = Ea * Ec - Eb * Eb
            if trace:
                t0, t1 = A[i] + C[i], Ea + Ec
                pa, pb = t1 * c2, 2.0 * t0 * c2
                pc = t0 * c1 - t1 * (A[i] * C[i] - Bq[i] * Bq[i])
                root = np.sqrt(pb * pb - 4.0 * pa * pc)
                x = np.where(pb >= 0, (-pb - root) / (2.0 * pa), (2.0 * pc) / (root - pb))
            else:
                x = np.where(c2 < 0, -c1 / (2.0 * c2), np.nan)
            ya, yb, yc = A[i] + x * Ea, Bq[i] + x * Eb, C[i] + x * Ec
            q = ya * yc - yb * yb
            if trace:
                za, zb, zc = yc * yc + yb * yb, -yb * (ya + yc), ya * ya + yb * yb
                bound = _CI_TOL * S * (q * q)
            else:
                za, zb, zc = yc, -yb, ya
                bound = 2.0 * _CI_TOL * q
            G = [(A[k] - ya) * za + 2.0 * (Bq[k] - yb) * zb + (C[k] - yc) * zc for k in range(N)]
            ok = member[:, i] & member[:, j] & (x > 0) & (x < 1) & (q > 0)
            ok &= np.abs(G[i] - G[j]) <= bound
            mid = 0.5 * (G[i] + G[j])
            for k in range(N):
                if k != i and k != j:
                    ok &= G[k] - mid <= bound
            found += ok
            w[ok, i], w[ok, j] = 1.0 - x[ok], x[ok]
    return _split(w, rep), found == 1


def _ci_tests2(Ys: np.ndarray, trace: bool) -> tuple[np.ndarray, tuple | None]:
    """The tests of `_ci_omegas2` on one block of problems (any leading shape): its weights
    (NaN where the inputs together are singular) and the index (np.nonzero) of the problems
    that need more (None if none; their weights are left unset)."""
    N = Ys.shape[-3]
    # Entry by entry, each an array over the problems (views: the first operation reads them).
    a = [Ys[..., i, 0, 0] for i in range(N)]
    b = [0.5 * (Ys[..., i, 0, 1] + Ys[..., i, 1, 0]) for i in range(N)]
    c = [Ys[..., i, 1, 1] for i in range(N)]
    tr = (sum(a[1:], a[0]) + sum(c[1:], c[0])) / (2 * N)
    tr[~(tr > 0)] = 1.0
    inv = 1.0 / tr
    a, b, c = [x * inv for x in a], [x * inv for x in b], [x * inv for x in c]
    am, bm, cm = sum(a[1:], a[0]) / N, sum(b[1:], b[0]) / N, sum(c[1:], c[0]) / N
    solvable = _invertible2(am, bm, cm)
    # Gradient at w = 1/N, through the quadratic form of adj(Ybar)^2 (trace) or adj(Ybar).
    q0 = am * cm - bm * bm
    if trace:
        A, Bq, C = cm * cm + bm * bm, -bm * (am + cm), am * am + bm * bm
        bound = _CI_TOL * (am + cm) * q0
    else:
        A, Bq, C = cm, -bm, am
        bound = 2.0 * _CI_TOL * q0
    G = [(a[i] - am) * A + 2.0 * (b[i] - bm) * Bq + (c[i] - cm) * C for i in range(N)]
    Gmax, Gmin = G[0], G[0]
    for x in G[1:]:
        Gmax, Gmin = np.maximum(Gmax, x), np.minimum(Gmin, x)
    flat = Gmax - Gmin <= bound
    # End points: KKT at each input alone. Equal inputs give the same numbers, so they pass
    # or fail together; the answer is an end point when those that pass are all equal.
    S = (am + cm) / q0 if trace else 2.0
    diff = {(j, k): (a[j] - a[k], b[j] - b[k], c[j] - c[k]) for k in range(N) for j in range(k)}
    passed = []
    for k in range(N):
        qk = a[k] * c[k] - b[k] * b[k]
        if trace:
            A, Bq, C = c[k] * c[k] + b[k] * b[k], -b[k] * (a[k] + c[k]), a[k] * a[k] + b[k] * b[k]
            bound = _CI_TOL * S * (qk * qk)
        else:
            A, Bq, C = c[k], -b[k], a[k]
            bound = 2.0 * _CI_TOL * qk
        # A singular Y_k (q_k <= 0 or at rounding level) fails the test by itself unless every
        # input is blind along its null direction z (z^T (Y_j - Y_k) z = z^T Y_j z >= 0 must
        # be <= ~0), i.e. unless the problem has no answer at all (not solvable).
        ok = qk > 0
        for j in range(N):
            if j < k:
                da, db, dc = diff[j, k]
                ok &= da * A + 2.0 * db * Bq + dc * C <= bound
            elif j > k:  # D_jk = -D_kj
                da, db, dc = diff[k, j]
                ok &= da * A + 2.0 * db * Bq + dc * C >= -bound
        passed.append(ok)
    eq = {(j, k): (a[j] == a[k]) & (b[j] == b[k]) & (c[j] == c[k]) for (j, k) in diff}
    # One group: no two inputs that pass differ.
    one = passed[0].copy()
    for k in range(1, N):
        one |= passed[k]
    for (j, k), e in eq.items():
        one &= ~(passed[j] & passed[k]) | e
    npass = sum(p.astype(float) for p in passed)
    out = np.empty(Ys.shape[:-2])
    end = one & ~flat
    for i in range(N):
        out[..., i] = passed[i] / npass  # (garbage where not an end point)
    out[flat] = 1.0 / N
    out[~solvable] = np.nan
    left = np.nonzero(solvable & ~flat & ~end)
    return out, (left if left[0].size else None)


def ci_omega(covs: Sequence[np.ndarray], criterion: Criterion = "trace") -> np.ndarray:
    """Weights omega of covariance intersection for one set of estimates (see `ci_omegas`)."""
    return ci_omegas(spd_inv(np.stack(covs))[None], criterion)[0]


def ci_weights(
    covs: Sequence[np.ndarray], omega: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray]:
    """Covariance intersection ("safe fusion"): P^-1 = sum w_i P_i^-1, c_i = w_i P P_i^-1;
    with w = 1 it is Millman's formula.

    For any cross-correlation between the inputs, P bounds the true error covariance.
    """
    infos = [spd_inv(P) for P in covs]
    P = inv_or_nan(sum(w * Y for w, Y in zip(omega, infos, strict=True)))
    return [w * (P @ Y) for w, Y in zip(omega, infos, strict=True)], P
