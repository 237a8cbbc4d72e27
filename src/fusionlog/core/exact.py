"""Exact covariance analysis: the true error statistics of every architecture, without sampling.

An architecture compiled to a plan (see `architectures`) is a linear map of the data, so the joint
first and second moments of Z_k = [x_k; s_k] (true state and estimator state) propagate exactly:

    x_k = F_t x_{k-1} + w,                 s_k = T_k s_{k-1} + U_k (H_t x_k + v_k),

with the *true* model (F_t, GQG_t, H_t, R_t, initial distribution), which may differ from the model
the filter was built with (model-mismatch studies). The error e_k = x_k - O_k s_k then has mean
mu_k and covariance C_k, and the expected MSE matrix is C_k + mu_k mu_k^T; for track-to-track
architectures this is the joint covariance of all local filters' errors carried along.

For the smoother (FBS) the backward information vector is y_b,k = B_k x_k + eta_k with eta_k
independent of everything up to k; B_k and cov(eta_k) follow a backward recursion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import NumericalError
from .architectures import Plan
from .linalg import mT, numerical_errors, sym, wide_diagonal
from .model import System


@dataclass
class Expected:
    """Exact expected error statistics per step k = 0..K."""

    mse: np.ndarray  # (K+1, n, n): E[e e^T]
    bias: np.ndarray  # (K+1, n): E[e]
    P: np.ndarray  # (K+1, n, n): the covariance the architecture reports
    nees: np.ndarray  # (K+1,): E[e^T P^-1 e] = tr(P^-1 E[e e^T])
    dm: np.ndarray  # (K+1,): E[sqrt(e^T P^-1 e)], eq. (46)

    @property
    def mse_per_state(self) -> np.ndarray:
        """(K+1, n) expected MSE of each state component, the exact counterpart of eq. (44)."""
        return np.diagonal(self.mse, axis1=-2, axis2=-1).copy()


def _coupling(plan: Plan, truth: System) -> bool:
    """Whether the estimator state deviation zeta = s - D x depends on the true state x.

    For an estimator built on the true dynamics and measurement matrices (F and H; the noise
    covariances and the prior may differ), zeta_k = T zeta_{k-1} + (U H - D) w + U v exactly:
    the x terms cancel, so x, whose covariance grows without bound for a random walk, can be
    left out, avoiding a catastrophic cancellation. A different F or H keeps the x terms, however
    small the difference: its effect grows with x.
    """
    model = plan.system
    if model is None:
        return True
    same_F = np.array_equal(model.F, truth.F) and (
        model.Fs is truth.Fs or (model.Fs is not None and np.array_equal(model.Fs, truth.Fs))
    )
    return not (same_F and np.array_equal(model.H, truth.H))


def _forward_moments(plan: Plan, truth: System) -> tuple[list, list, int, int]:
    """Mean and covariance of Z_k = [x_k; zeta_k], zeta_k = s_k - D_k x_k, for every k.

    Returns the lists, the size of the x block (0 when x decouples, see `_coupling`) and the
    step from which the moments and the plan's map repeat (K + 1 if they never settle): once
    the plan repeats its steady-state map and the moments stop changing, later steps repeat
    them too (the same objects in the lists).
    """
    if plan.per_run:
        raise ValueError("exact analysis needs a plan shared by all runs (no missing data)")
    n = truth.n
    Ht, Rt = truth.H, truth.R
    init = truth.truth_initial
    nx = n if _coupling(plan, truth) else 0
    D0 = plan.D0
    # Before the first update: x_0 ~ init, zeta_{-1} = s0 - D0 x_0.
    Jx = np.vstack([np.eye(n), -D0])[n - nx :] if nx else -D0
    mu = np.concatenate([init.mean, plan.s0 - D0 @ init.mean])[n - nx :]
    C = Jx @ init.cov @ Jx.T
    mus, Cs = [], []
    D_prev = D0
    K1 = len(plan.steps)
    for k, st in enumerate(plan.steps):
        d_prev = mu.size - nx
        d = st.T.shape[0]
        F = truth.F_at(k) if k > 0 else np.eye(n)
        UHD = st.U @ Ht - st.D
        A = np.zeros((nx + d, nx + d_prev))
        A[nx:, nx:] = st.T
        Bw = UHD
        if nx:
            A[:nx, :nx] = F
            A[nx:, :nx] = st.T @ D_prev + UHD @ F
            Bw = np.vstack([np.eye(n), UHD])
        Bv = np.zeros((nx + d, Rt.shape[0]))
        Bv[nx:] = st.U
        mu_new = A @ mu
        C_new = A @ C @ A.T + Bv @ Rt @ Bv.T
        if k > 0:
            C_new += Bw @ truth.GQG_at(k) @ Bw.T
        C_new = sym(C_new)
        if (
            not nx
            and k > 1
            and st is plan.steps[k - 1]
            and np.abs(C_new - C).max() <= 1e-15 * np.abs(C_new).max()
            and np.abs(mu_new - mu).max() <= 1e-15 * max(np.abs(mu_new).max(), 1e-300)
        ):
            mus.extend([mu_new] * (K1 - k))
            Cs.extend([C_new] * (K1 - k))
            return mus, Cs, nx, k
        mu, C = mu_new, C_new
        mus.append(mu)
        Cs.append(C)
        D_prev = st.D
    # A non-finite entry stays non-finite (inf * 0 and inf - inf are NaN): the last step tells.
    if not (np.isfinite(C).all() and np.isfinite(mu).all()):
        k = next(
            k
            for k, (m, c) in enumerate(zip(mus, Cs, strict=True))
            if not np.isfinite(c).all() or not np.isfinite(m).all()
        )
        raise NumericalError(f"step {k}: the true error covariance overflows")
    return mus, Cs, nx, K1


def analyse(plan: Plan, truth: System) -> Expected:
    """Exact error mean, MSE matrix, expected NEES and expected DM of a shared plan.

    Raises NumericalError (naming the architecture and the step) when the true error
    covariance overflows or the reported covariance is not positive definite where the
    architecture reports one, i.e. when the expected values cannot be computed.
    """
    with numerical_errors(lambda: f"architecture {plan.name}, exact analysis"):
        ex = _analyse(plan, truth)
        defined = np.isfinite(ex.P).all(axis=(-2, -1))
        finite = np.isfinite(ex.mse).all(axis=(-2, -1)) & np.isfinite(ex.nees) & np.isfinite(ex.dm)
        if not finite[defined].all():
            k = int(np.flatnonzero(defined & ~finite)[0])
            raise NumericalError(
                f"step {k}: the expected MSE, NEES or DM is not finite (the reported "
                "covariance is not positive definite to working precision, or the error "
                "covariance overflows)"
            )
    return ex


def _analyse(plan: Plan, truth: System) -> Expected:
    n = truth.n
    mus, Cs, nx, settled = _forward_moments(plan, truth)
    K1 = len(plan.steps)

    def readout(k: int, A: np.ndarray, D: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """Row block L with e = L Z - (noise terms): e = (I - A D - extra) x - A zeta."""
        if nx:
            return np.hstack([np.eye(n) - A @ D - extra, -A])
        return -A

    bias = np.empty((K1, n))
    mse = np.empty((K1, n, n))
    if plan.smoother is None:
        for k, st in enumerate(plan.steps[: settled + 1]):
            Lk = readout(k, st.O, st.D, 0.0)
            bias[k] = Lk @ mus[k]
            mse[k] = sym(Lk @ Cs[k] @ Lk.T) + np.outer(bias[k], bias[k])
        if settled < K1:  # steady state: the same map of the same moments at every later step
            bias[settled + 1 :], mse[settled + 1 :] = bias[settled], mse[settled]
    else:
        sm = plan.smoother
        Ht, Rt = truth.H, truth.R
        Bk = np.zeros((n, n))
        Ceta = np.zeros((n, n))
        steady = False  # backward statistics stopped changing under a repeated map
        # repeated[k]: step k's backward map is step k + 1's; same[k]: and so is everything
        # step k's statistics are made of, so in the steady state they are step k + 1's.
        repeated = [sm.L[k] is sm.L[k + 1] and sm.V[k + 1] is sm.V[k + 2] for k in range(K1 - 2)]
        repeated += [False, False]
        same = [
            rep and a is a1 and b is b1 and s is s1 and m is m1 and c is c1
            for rep, a, a1, b, b1, s, s1, m, m1, c, c1 in zip(
                repeated,
                sm.A, sm.A[1:], sm.B, sm.B[1:], plan.steps, plan.steps[1:],
                mus, mus[1:], Cs, Cs[1:], strict=False,  # the shifted lists are one shorter
            )
        ]  # fmt: skip
        same += [False]
        # run_start[k]: first step of the stretch of `same` steps that ends at k
        idx = np.arange(K1)
        run_start = np.maximum.accumulate(np.where(same, -1, idx)) + 1
        k = K1 - 1
        while k >= 0:
            steady = steady and repeated[k]
            if steady and same[k]:  # the steady stretch repeats step k + 1's statistics
                j = int(run_start[k])
                bias[j : k + 1], mse[j : k + 1] = bias[k + 1], mse[k + 1]
                k = j - 1
                continue
            if k < K1 - 1 and not steady:
                Bplus = Bk + sm.V[k + 1] @ Ht
                Cplus = Ceta + sm.V[k + 1] @ Rt @ sm.V[k + 1].T
                # L is about the inverse of the information in B+ and C+: multiplying it in
                # first keeps B+ Q B+' (the square of an information) from overflowing.
                LB = sm.L[k] @ Bplus
                B_new = LB @ truth.F_at(k + 1)
                C_new = sym(LB @ truth.GQG_at(k + 1) @ LB.T + sm.L[k] @ Cplus @ sm.L[k].T)
                steady = repeated[k] and all(
                    np.abs(new - old).max() <= 1e-15 * max(np.abs(new).max(), 1e-300)
                    for new, old in ((B_new, Bk), (C_new, Ceta))
                )
                Bk, Ceta = B_new, C_new
            # e = x - A s_f - B (B_k x + eta) = (I - A D - B B_k) x - A zeta - B eta; with the
            # true model I - A D - B B_k vanishes and B_k x is dropped with x (see _coupling).
            Lk = readout(k, sm.A[k], plan.steps[k].D, sm.B[k] @ Bk)
            bias[k] = Lk @ mus[k]
            mse[k] = sym(Lk @ Cs[k] @ Lk.T + sm.B[k] @ Ceta @ sm.B[k].T) + np.outer(
                bias[k], bias[k]
            )
            k -= 1
    P = plan.reported_cov
    nees = np.full(K1, np.nan)
    dm = np.full(K1, np.nan)
    # A filter's statistics and reported covariance repeat after `settled`: compute them once.
    m = settled + 1 if plan.smoother is None and settled < K1 else K1
    ok = ~np.isnan(P[:m]).any(axis=(-1, -2))
    if ok.any():
        Pk, bk, mk = P[:m][ok], bias[:m][ok], mse[:m][ok]
        definite = np.isfinite(_whitening(Pk)).all(axis=(-2, -1))
        if not definite.all():
            k = int(np.flatnonzero(ok)[np.argmin(definite)])
            raise NumericalError(
                f"step {k}: the reported covariance is not positive definite to working "
                "precision (no NEES or DM)"
            )
        # For badly scaled P (see _whitening) P^-1 = W^T W; otherwise LU's inverse, as ever.
        Linv = _whitening(Pk) if wide_diagonal(Pk) else None
        Pinv = np.linalg.inv(Pk) if Linv is None else mT(Linv) @ Linv
        nees[:m][ok] = np.einsum("kij,kji->k", Pinv, mk)
        cov = mk - np.einsum("ki,kj->kij", bk, bk)
        # Steady-state steps repeat the same statistics: integrate each distinct one once.
        key = np.concatenate([Pk.reshape(len(Pk), -1), bk, cov.reshape(len(cov), -1)], 1)
        uniq, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        dm_u = expected_sqrt_quadratic(Pk[first], bk[first], cov[first])
        dm[:m][ok] = dm_u[inverse.ravel()]
    nees[m:], dm[m:] = nees[m - 1], dm[m - 1]
    return Expected(mse, bias, P, nees, dm)


def expected_sqrt_quadratic(
    P: np.ndarray, mean: np.ndarray, cov: np.ndarray, nodes: int = 1601
) -> np.ndarray:
    """E[sqrt(e^T P^-1 e)] for e ~ N(mean, cov), batched over the leading axis.

    Uses sqrt(q) = 1/(2 sqrt(pi)) * int_0^inf (1 - exp(-t q)) t^-3/2 dt and the moment generating
    function of a Gaussian quadratic form, E exp(-t q) = prod_i (1 + 2 t l_i)^-1/2
    exp(-t b_i^2 / (1 + 2 t l_i)), with l_i the eigenvalues of P^-1/2 cov P^-1/2 and b the whitened
    mean in their eigenbasis. After t = exp(u) the integrand is smooth and decays exponentially
    at both ends, so the trapezoidal rule on a wide uniform grid is accurate to rounding.
    For a consistent filter (mean 0, cov = P) this is the chi mean sqrt(2) G((n+1)/2) / G(n/2).
    """
    out = np.full(P.shape[0], np.nan)
    Linv = _whitening(P)
    good = np.isfinite(Linv).all(axis=(-2, -1))
    if not good.all():  # P not positive definite (to working precision): DM undefined (NaN)
        Linv, mean, cov, P = Linv[good], mean[good], cov[good], P[good]
    W = Linv @ cov @ mT(Linv)
    lam, V = np.linalg.eigh(sym(W))
    lam = np.clip(lam, 0.0, None)
    b = np.einsum("kji,kj->ki", V, np.einsum("kij,kj->ki", Linv, mean))
    u = np.linspace(-60.0, 60.0, nodes)
    t = np.exp(u)
    res = np.empty(P.shape[0])
    for k0 in range(0, P.shape[0], 256):
        sl = slice(k0, k0 + 256)
        tl = t[None, :, None] * lam[sl, None, :]
        log_mgf = -0.5 * np.log1p(2.0 * tl) - t[None, :, None] * b[sl, None, :] ** 2 / (1 + 2 * tl)
        one_minus = -np.expm1(log_mgf.sum(axis=-1))
        integrand = one_minus * np.exp(-0.5 * u)[None, :]
        res[sl] = np.trapezoid(integrand, u, axis=-1) / (2.0 * np.sqrt(np.pi))
    out[good] = res
    return out


def _whitening(P: np.ndarray) -> np.ndarray:
    """W with W^T W = P^-1 for each P of a batch: the inverse Cholesky factor, or, where the
    factorisation fails on a matrix that rounding left barely definite, diag(w)^-1/2 V^T from
    its eigen-decomposition (any such W gives the same quadratic form); NaN where P is not
    positive definite.

    A P whose diagonal spans more than 1e8 (a position known to 1e-150 beside a velocity known
    to 0.1) is Jacobi-scaled first, P = D^1/2 Ps D^1/2 and W = chol(Ps)^-1 D^-1/2: the LU
    inverse of its own Cholesky factor would put rounding garbage of 1e134 where a zero is.
    The others are scaled by 1, which leaves their numbers as they were.
    """
    d = P.diagonal(0, -2, -1)
    lo, hi = d.min(axis=-1), d.max(axis=-1)
    wide = (lo > 0) & (hi > 1e8 * lo)
    if wide.any():
        s = 1.0 / np.sqrt(np.where(wide[..., None], d, 1.0))
        return _whitening(P * (s[..., :, None] * s[..., None, :])) * s[..., None, :]
    try:
        return np.linalg.inv(np.linalg.cholesky(P))
    except np.linalg.LinAlgError:
        finite = np.isfinite(P).all(axis=(-2, -1))
        w, V = np.linalg.eigh(np.where(finite[..., None, None], P, np.eye(P.shape[-1])))
        pd = finite & (w[..., 0] > 0)
        s = 1.0 / np.sqrt(np.where(pd[..., None], w, 1.0))
        return np.where(pd[..., None, None], s[..., :, None] * mT(V), np.nan)
