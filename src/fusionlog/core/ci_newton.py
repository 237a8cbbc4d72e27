"""Covariance intersection's weights by Newton's method on the faces of the simplex.

The cost tr P or log det P, P = (sum_i w_i Y_i)^-1, is convex in w on the simplex; on a face
(the inputs left in) an equality-constrained Newton step with gradient d tr P / d w_i =
-tr(P Y_i P) and Hessian 2 tr(P Y_i P Y_j P) (for log det P: -tr(P Y_i), tr(P Y_i P Y_j)),
a modified LDL^T solve, steps cut at the boundary, Armijo backtracking, and inputs released
by their KKT multipliers, for B independent problems at once with per-problem convergence (so
a problem's answer does not depend on the others in its batch). `fusionlog.core.ci` decides
which problems need it.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .linalg import mT

Criterion = Literal["trace", "det"]

#: Newton iterations at most per covariance-intersection problem (3 to 12 are typical; an
#: optimum with a weight of 1e-10 or less, far from the start 1/N, can take more).
CI_MAXITER = 100
#: A face of the simplex is solved when the cost's gradient varies over its inputs by at most
#: CI_TOL times the cost scale (the cost is then within that of the face's optimum, by
#: convexity), or when the Newton decrement is below _CI_DEC times it: the cost is then within
#: half of that, and the last Newton step, if shorter than _CI_POLISH, is taken without a line
#: search (whose costs would differ by rounding only), for an omega accurate to about the
#: square of that step. An input left out comes back when moving weight to it lowers the
#: cost faster than CI_TOL times the scale.
CI_TOL = 1e-13
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


def rowsum(x: np.ndarray) -> np.ndarray:
    """x[:, 0] + x[:, 1] + ... in that order, (B, N) -> (B,). Written out rather than
    x.sum(axis=1): numpy may reduce a small axis in a different order depending on the other
    axes' sizes, which would make a problem's rounding depend on how many share the batch."""
    s = x[:, 0]
    for i in range(1, x.shape[1]):
        s = s + x[:, i]
    return s


def diagsum(X: np.ndarray) -> np.ndarray:
    """Trace over the last two axes, added in index order (see `rowsum`)."""
    s = X[..., 0, 0]
    for a in range(1, X.shape[-1]):
        s = s + X[..., a, a]
    return s


class Info2:
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
    def of(cls, a: np.ndarray, b: np.ndarray, c: np.ndarray, trace: bool) -> Info2:
        """From the entries [[a_i, b_i], [b_i, c_i]] of the informations, each (B, N)."""
        N = a.shape[1]
        am, bm, cm = rowsum(a) / N, rowsum(b) / N, rowsum(c) / N
        da, db, dc = a - am[:, None], b - bm[:, None], c - cm[:, None]
        Q = 0.5 * (da[:, :, None] * dc[:, None, :] + dc[:, :, None] * da[:, None, :])
        Q = Q - db[:, :, None] * db[:, None, :]
        lin = cm[:, None] * da + am[:, None] * dc - 2.0 * bm[:, None] * db
        return cls(trace, am * cm - bm * bm, am + cm, lin, da + dc, Q)

    def take(self, rows: np.ndarray) -> Info2:
        return Info2(
            self.trace, self.q0[rows], self.t0[rows], self.lin[rows], self.s[rows], self.Q[rows]
        )

    def _q(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Qw = self.Q[:, :, 0] * w[:, :1]
        for j in range(1, w.shape[1]):
            Qw = Qw + self.Q[:, :, j] * w[:, j : j + 1]
        return self.q0 + rowsum(w * (self.lin + Qw)), Qw

    def value(self, w: np.ndarray) -> np.ndarray:
        q, _ = self._q(w)
        if not self.trace:
            return q
        return np.where(q > 0, (self.t0 + rowsum(self.s * w)) / q, np.inf)

    def derivs(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Key, gradient and Hessian in omega. With v = grad q = l + 2 Q w:
        tr P: g = s/q - t v/q^2, H = (2 f (v v^T - q Q) - s v^T - v s^T)/q^2 (f = t/q);
        log det P: g = -v/q, H = (v v^T/q - 2 Q)/q."""
        q, Qw = self._q(w)
        v = self.lin + 2.0 * Qw
        iq = 1.0 / q
        vv = v[:, :, None] * v[:, None, :]
        if self.trace:
            f = (self.t0 + rowsum(self.s * w)) * iq
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


class InfoN:
    """Costs of CI problems of any n with matrices: Y(w) = Ybar + sum_i w_i D_i (centred as in
    `Info2`), P = Y(w)^-1 by LU, and with M_i = P D_i, C_i = M_i P:
    tr P: g_i = -tr C_i, H_ij = 2 tr(M_i C_j); log det P: g_i = -tr M_i, H_ij = tr(M_i M_j).
    Keys: tr P or -log det P (lower is better, inf where Y(w) is not positive definite). Every
    product is a matmul or LAPACK call per matrix, so each problem's numbers are its own."""

    def __init__(self, trace: bool, Ybar: np.ndarray, D: np.ndarray) -> None:
        self.trace, self.Ybar, self.D = trace, Ybar, D
        self.n = Ybar.shape[-1]

    @classmethod
    def of(cls, Ys: np.ndarray, trace: bool) -> InfoN:
        Ybar = Ys[:, 0]
        for i in range(1, Ys.shape[1]):
            Ybar = Ybar + Ys[:, i]
        Ybar = Ybar / Ys.shape[1]
        return cls(trace, Ybar, Ys - Ybar[:, None])

    def take(self, rows: np.ndarray) -> InfoN:
        return InfoN(self.trace, self.Ybar[rows], self.D[rows])

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
        return np.where(ok, diagsum(P) if self.trace else -logdet, np.inf)

    def derivs(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ok, logdet, P = self._inv(w)
        B, N, n = self.D.shape[:3]
        M = P[:, None] @ self.D
        if self.trace:
            C = M @ P[:, None]
            f, g = diagsum(P), -diagsum(C)
            Ct = np.ascontiguousarray(mT(C)).reshape(B, N, n * n)
            H = 2.0 * (M.reshape(B, N, n * n) @ mT(Ct))
        else:
            f, g = -logdet, -diagsum(M)
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
    nf = rowsum(m)
    gm = rowsum(g * m) / nf
    gp = (g - gm[:, None]) * m
    r = H[:, :, 0] * m[:, :1]
    for j in range(1, N):
        r = r + H[:, :, j] * m[:, j : j + 1]
    r = r / nf[:, None]
    c = rowsum(r * m) / nf
    mm = m[:, :, None] * m[:, None, :]
    Hp = (H - r[:, :, None] - r[:, None, :] + c[:, None, None]) * mm
    sigma = diagsum(Hp) / np.maximum(nf - 1.0, 1.0)
    sigma = np.where(sigma > 1e-250, sigma, 1.0)
    K = Hp + (sigma / nf)[:, None, None] * mm
    K[:, np.arange(N), np.arange(N)] += 1.0 - m
    d = -_ldl_solve(K, gp) * m
    d = d - m * (rowsum(d) / nf)[:, None]  # back onto 1^T d = 0 after rounding
    dec = -rowsum(gp * d)
    spread = np.where(free, g, -np.inf).max(axis=1) - np.where(free, g, np.inf).min(axis=1)
    return d, dec, gm, spread


def newton_solve(ev: Info2 | InfoN, w: np.ndarray, member: np.ndarray) -> np.ndarray:
    """Active-set Newton method for B CI problems from the start points w, each on its own.

    The free inputs F (a face of the simplex) start as `member`. Each iteration takes, for every
    unfinished problem, the Newton step on its face (`_newton_direction`), cut where a weight
    would turn negative, and backtracks (halving) until Armijo's decrease holds; a weight the
    cut step puts at 0 leaves F. A problem whose face is solved (see CI_TOL, _CI_DEC) checks
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
        solved = ~(spread > CI_TOL * S) | ~(dec > _CI_DEC * S) | stuck
        mu = np.where(member & ~free, g - gm[:, None], np.inf)
        j = np.argmin(mu, axis=1)
        release = solved & (mu[at, j] < -CI_TOL * S) & ~locked
        free[at[release], j[release]] = True
        stuck &= ~release
        finished = solved & ~release
        # The last Newton step where the decrement (not the gradient's spread) ended it.
        polish = finished & (spread > CI_TOL * S) & (dec <= _CI_DEC * S)
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
    return wt / rowsum(wt)[:, None]


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


def invertible2(a: np.ndarray, b: np.ndarray, c: np.ndarray, rtol: float = 1e-13) -> np.ndarray:
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


def representatives(equal, B: int, N: int) -> np.ndarray:
    """rep (B, N): for each input the first input bit-for-bit equal to it (`equal(k, i)`, a
    boolean per problem)."""
    rep = np.empty((B, N), dtype=np.intp)
    for k in range(N):
        r = np.full(B, k)
        for i in reversed(range(k)):
            r[equal(k, i)] = i
        rep[:, k] = r
    return rep


def finish(ev: Info2 | InfoN, rep: np.ndarray) -> np.ndarray:
    """Newton from the merged start (each group of equal inputs as one, weight count/N), the
    end-point rule, and the weights split equally within each group."""
    B, N = rep.shape
    member = rep == np.arange(N)
    count = np.stack([rowsum((rep == i).astype(float)) for i in range(N)], axis=1)
    w = newton_solve(ev, np.where(member, count / N, 0.0), member)
    # End points: an input alone wins only if better by more than rounding.
    best = ev.value(w)
    for i in range(N):
        e = np.zeros((B, N))
        e[:, i] = 1.0
        win = member[:, i] & ev.better(ev.value(e), best)
        if win.any():
            w[win] = e[win]
            best = np.where(win, ev.value(w), best)
    return split(w, rep)


def split(w: np.ndarray, rep: np.ndarray) -> np.ndarray:
    """Weights of the merged problems (on each group's first input) shared equally within each
    group of equal inputs."""
    B, N = rep.shape
    if (rep == np.arange(N)).all():
        return w
    count = np.stack([rowsum((rep == i).astype(float)) for i in range(N)], axis=1)
    at = np.arange(B)[:, None]
    return w[at, rep] / count[at, rep]
