"""E[sqrt(e^T P^-1 e)] for Gaussian e: the expected Mahalanobis distance (DM, eq. 46) of an
architecture whose error is e ~ N(mean, cov) and which reports P.

The integrals use sqrt(q) = 1/(2 sqrt(pi)) int_0^inf (1 - exp(-t q)) t^-3/2 dt and the moment
generating function of a Gaussian quadratic form,

    M(t) = E exp(-t q) = prod_i (1 + 2 t l_i)^-1/2 exp(-t b_i^2 / (1 + 2 t l_i)),

with l_i the eigenvalues of P^-1/2 cov P^-1/2 and b the whitened mean in their eigenbasis. After
t = exp(u) the integrand g(u) = (1 - M(e^u)) e^(-u/2) is smooth and decays exponentially at both
ends. `expected_sqrt_quadratic` takes the trapezoidal rule on a wide fixed grid (the few
distinct statistics of a shared plan). `nees_and_dm_many` (every run and step of a per-run
analysis) takes closed forms where there are some (one state: the folded normal mean; two
states without a mean: a complete elliptic integral) and otherwise the trapezoidal rule on a grid
fitted to each item with its infinite tails summed in closed form, some thirty to eighty times
fewer nodes for the same accuracy.
"""

from __future__ import annotations

from math import comb, factorial

import numpy as np

from .linalg import mT, sym


def expected_sqrt_quadratic(
    P: np.ndarray, mean: np.ndarray, cov: np.ndarray, nodes: int = 1601
) -> np.ndarray:
    """E[sqrt(e^T P^-1 e)] for e ~ N(mean, cov), batched over the leading axis.

    The trapezoidal rule on u in [-60, 60] (module docstring): accurate to rounding for any
    spread of the eigenvalues. For a consistent filter (mean 0, cov = P) this is the chi mean
    sqrt(2) G((n+1)/2) / G(n/2).
    """
    out = np.full(P.shape[0], np.nan)
    good, lam, b = _whitened(P, mean, cov)
    out[good] = _fixed_grid(lam, b, nodes)
    return out


def _fixed_grid(lam: np.ndarray, b: np.ndarray, nodes: int = 1601) -> np.ndarray:
    """The trapezoidal rule on u in [-60, 60] for items of eigenvalues l and mean b (N, n)."""
    u = np.linspace(-60.0, 60.0, nodes)
    t = np.exp(u)
    res = np.empty(lam.shape[0])
    for k0 in range(0, lam.shape[0], 256):
        sl = slice(k0, k0 + 256)
        tl = t[None, :, None] * lam[sl, None, :]
        log_mgf = -0.5 * np.log1p(2.0 * tl) - t[None, :, None] * b[sl, None, :] ** 2 / (1 + 2 * tl)
        one_minus = -np.expm1(log_mgf.sum(axis=-1))
        integrand = one_minus * np.exp(-0.5 * u)[None, :]
        res[sl] = np.trapezoid(integrand, u, axis=-1) / (2.0 * np.sqrt(np.pi))
    return res


def _whitened(P: np.ndarray, mean: np.ndarray, cov: np.ndarray, Linv: np.ndarray | None = None):
    """(good, l, b): which P are positive definite (to working precision; DM is undefined, NaN,
    for the others), and for those the eigenvalues l >= 0 of W cov W^T (W^T W = P^-1, `Linv`
    if given, else `whitening`) and the whitened mean W mean in their eigenbasis."""
    if Linv is None:
        Linv = whitening(P)
    good = np.isfinite(Linv).all(axis=(-2, -1))
    if not good.all():
        Linv, mean, cov = Linv[good], mean[good], cov[good]
    W = Linv @ cov @ mT(Linv)
    lam, V = np.linalg.eigh(sym(W))
    lam = np.clip(lam, 0.0, None)
    b = np.einsum("kji,kj->ki", V, np.einsum("kij,kj->ki", Linv, mean))
    return good, lam, b


#: Trapezoid steps in u: the error of the rule on the whole line falls like exp(-2 pi d / h),
#: d the half-width of the strip around the real axis where g is analytic. Without a mean the
#: nearest singularities are the branch points of (1 + 2 t l)^-1/2 at Im u = pi: h = 0.5 gives
#: rounding. A mean adds exp(-t b^2 / (1 + 2 t l)), which grows off the axis beyond Im u = pi/2
#: (for b^2 >> l like exp(+|t| b^2)): h = 0.3 gives rounding there (checked up to b^2/l = 1e10).
_H_CENTRED, _H_MEAN = 0.5, 0.3
#: Where the tails start: t sigma <= _LOW below (with _LOW_TERMS terms of the series of
#: 1 - M(t) in t), 2 t l_min >= _HIGH max(1, b^2/l) above (_HIGH_TERMS terms in 1/t): what they
#: leave out is below 1e-16 of the total.
_LOW, _HIGH = 3e-2, 1e2
_LOW_TERMS, _HIGH_TERMS = 10, 8
#: Items needing more nodes (eigenvalues spread over 1e60) take the fixed grid.
_MAX_NODES = 600


def nees_and_dm_many(
    P: np.ndarray, mean: np.ndarray, mse: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expected NEES tr(P^-1 E[e e^T]) and DM E[sqrt(e^T P^-1 e)] (eq. 46) of a large batch of
    errors e ~ N(mean, mse - mean mean^T) against reported covariances P (N, n, n), and which P
    are positive definite to working precision (NEES and DM are NaN for the others).

    With W^T W = P^-1 and G = W cov W^T = V diag(l) V^T: NEES = sum_i l_i + |W mean|^2, and DM
    from l and b = V^T W mean (`expected_sqrt_quadratic_many`). For n <= 2 the Cholesky factor,
    its inverse and the eigen-decomposition are written out, vectorised over the batch (LAPACK
    takes as long to be called on a 2 x 2 matrix as to factor it).
    """
    n = P.shape[-1]
    cov = mse - mean[..., :, None] * mean[..., None, :]
    if n > 2:
        good, lam, b = _whitened(P, mean, cov)
    else:
        good, (lam, b) = _spectrum_small(P, mean, cov)
        retry = ~good & np.isfinite(P).all(axis=(-2, -1))
        if retry.any():  # barely definite: `whitening`'s eigen-decomposition may accept it
            ok, lr, br = _whitened(P[retry], mean[retry], cov[retry])
            if ok.any():
                good_r = np.flatnonzero(retry)[ok]
                lam, b = _insert(lam, b, good, good_r, lr, br)
                good[good_r] = True
    nees = np.full(P.shape[0], np.nan)
    dm = np.full(P.shape[0], np.nan)
    nees[good] = lam.sum(axis=-1) + (b * b).sum(axis=-1)
    dm[good] = _spectral_dm(lam, b)
    return nees, dm, good


def expected_sqrt_quadratic_many(
    P: np.ndarray, mean: np.ndarray, cov: np.ndarray, whitening: np.ndarray | None = None
) -> np.ndarray:
    """`expected_sqrt_quadratic` for a large batch (N, n, n), to ~1e-15 (`_spectral_dm`).
    `whitening`: `whitening(P)` when the caller has it."""
    out = np.full(P.shape[0], np.nan)
    good, lam, b = _whitened(P, mean, cov, whitening)
    out[good] = _spectral_dm(lam, b)
    return out


def _insert(lam, b, good, extra, lam_x, b_x):
    """The spectra (l, b) of the items `good` with those of the items `extra` merged in, in
    item order."""
    both = good.copy()
    both[extra] = True
    L = np.empty((int(both.sum()), lam.shape[1]))
    B = np.empty_like(L)
    pos = np.cumsum(both) - 1
    L[pos[good]], B[pos[good]] = lam, b
    L[pos[extra]], B[pos[extra]] = lam_x, b_x
    return L, B


def _spectrum_small(P: np.ndarray, mean: np.ndarray, cov: np.ndarray):
    """`_whitened` for n = 1 or 2, written out over the batch: (good, (l, b)).

    n = 2: P = L L^T with L = [[a, 0], [c, d]], a = sqrt(p00), c = p01 / a,
    d = sqrt(p11 - c^2) (P is positive definite where a and d^2 are positive, as for LAPACK's
    Cholesky); W = L^-1 = [[1/a, 0], [-c/(a d), 1/d]]; the eigenvalues of the symmetric 2 x 2
    G = W cov W^T as LAPACK's dlaev2 takes them (the smaller as det G / the larger, which keeps
    its relative accuracy), the eigenvector of the larger at angle theta, tan 2 theta =
    2 g01 / (g00 - g11).
    """
    if P.shape[-1] == 1:
        p = P[:, 0, 0]
        good = p > 0
        w = 1.0 / np.sqrt(p[good])
        lam = np.clip(cov[good, 0, 0], 0.0, None) * w * w
        return good, (lam[:, None], (mean[good, 0] * w)[:, None])
    p00, p01, p11 = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.sqrt(p00)
        c = p01 / a
        d2 = p11 - c * c
    good = (p00 > 0) & (d2 > 0)
    if not good.all():
        a, c, d2 = a[good], c[good], d2[good]
        mean, cov = mean[good], cov[good]
    d = np.sqrt(d2)
    w00, w10, w11 = 1.0 / a, -c / (a * d), 1.0 / d
    c00, c01, c11 = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    g00 = w00 * w00 * c00
    g01 = w00 * (w10 * c00 + w11 * c01)
    g11 = w10 * w10 * c00 + 2.0 * w10 * w11 * c01 + w11 * w11 * c11
    half = 0.5 * (g00 + g11)
    r = np.hypot(0.5 * (g00 - g11), g01)
    l1 = half + r
    with np.errstate(invalid="ignore", divide="ignore"):
        l2 = np.where(l1 > 0, (g00 * g11 - g01 * g01) / l1, 0.0)
    lam = np.clip(np.stack([l2, l1], axis=-1), 0.0, None)  # ascending, as eigh
    m0 = w00 * mean[:, 0]
    m1 = w10 * mean[:, 0] + w11 * mean[:, 1]
    theta = 0.5 * np.arctan2(2.0 * g01, g00 - g11)
    cs, sn = np.cos(theta), np.sin(theta)
    b = np.stack([cs * m1 - sn * m0, cs * m0 + sn * m1], axis=-1)
    return good, (lam, b)


def _spectral_dm(lam: np.ndarray, b: np.ndarray) -> np.ndarray:
    """E sqrt(q), q = sum_i l_i (xi_i + b_i / sqrt(l_i))^2 (xi standard normal), for items
    (N, n) of eigenvalues l >= 0 and whitened mean b in their eigenbasis.

    Closed forms: n = 1, E|X| for X ~ N(b, l), sqrt(2 l / pi) exp(-b^2 / (2 l)) + b erf(b /
    sqrt(2 l)) (the folded normal mean); n = 2 with b = 0, in polar coordinates E sqrt(l1 x^2 +
    l2 y^2) = E[r] E_phi sqrt(l1 cos^2 + l2 sin^2) = sqrt(2 l1 / pi) E(1 - l2 / l1), l1 >= l2, E
    the complete elliptic integral of the second kind. The others: the trapezoidal rule on the
    whole line in u = log t, h sum_j g(u_lo + j h), j in Z, of which only the nodes from u_lo up
    to u_top are evaluated (`_node_sum`) and the two infinite tails are geometric series in
    closed form (`_tail_sums`): some twenty to sixty nodes an item. Items with a singular
    whitened covariance (some l_i = 0: another upper tail) or eigenvalues spread too far for
    the grid take the fixed grid of `expected_sqrt_quadratic`.
    """
    from scipy import special  # here: ~0.25 s of import that only an evaluation needs

    N, n = lam.shape
    res = np.full(N, np.nan)
    b2 = b * b
    lT, bT = np.ascontiguousarray(lam.T), np.ascontiguousarray(b2.T)
    done = np.zeros(N, dtype=bool)
    if n == 1:
        l0, m = lT[0], b[:, 0]
        with np.errstate(invalid="ignore", divide="ignore", under="ignore"):
            s = np.sqrt(2.0 * l0)
            res = np.where(
                l0 > 0,
                s / np.sqrt(np.pi) * np.exp(-(m * m) / (s * s)) + m * special.erf(m / s),
                np.abs(m),
            )
        return res
    if n == 2:
        done = (bT == 0.0).all(axis=0)
        l_small, l_big = lT.min(axis=0)[done], lT.max(axis=0)[done]
        with np.errstate(invalid="ignore", divide="ignore"):
            m = 1.0 - np.where(l_big > 0, l_small / l_big, 1.0)
        res[done] = np.sqrt(2.0 * l_big / np.pi) * special.ellipe(m)
    # (n, N) for the per-item reductions: numpy reduces a short trailing axis slowly
    regular = (lT > 0).all(axis=0)
    ls = np.where(regular, lT, 1.0)
    ratio = (bT / ls).max(axis=0, initial=0.0)
    h = np.where(ratio > 1.0, _H_MEAN, _H_CENTRED)
    u_lo = np.log(_LOW / (2.0 * ls.sum(axis=0) + bT.sum(axis=0)))
    u_hi = np.log(_HIGH * np.maximum(1.0, ratio) / (2.0 * ls.min(axis=0)))
    count = np.ceil((u_hi - u_lo) / h).astype(np.int64)
    fast = regular & (count <= _MAX_NODES) & ~done
    slow = ~fast & ~done
    if slow.any():
        res[slow] = _fixed_grid(lam[slow], b[slow])
    idx = np.flatnonzero(fast)
    if idx.size:
        # Items of one step size and similar node counts together: each chunk evaluates as
        # many nodes as its most demanding item (more only moves an item's upper tail out).
        idx = idx[np.lexsort((count[idx], h[idx]))]
        lam, b2, h, u_lo, count = lam[idx], b2[idx], h[idx], u_lo[idx], count[idx]
        total = np.empty(idx.size)
        for hs in np.unique(h):
            group = np.flatnonzero(h == hs)
            nodes = np.empty(group.size, dtype=np.int64)
            for c0 in range(0, group.size, 2048):
                part = group[c0 : c0 + 2048]
                nodes[c0 : c0 + 2048] = count[part].max()
                total[part] = _node_sum(lam[part], b2[part], float(hs), u_lo[part], nodes[c0])
            lg, bg, ug = lam[group], b2[group], u_lo[group]
            total[group] += _tail_sums(lg, bg, float(hs), ug, ug + nodes * hs)
        res[idx] = h * total / (2.0 * np.sqrt(np.pi))
    return res


def _node_sum(lam: np.ndarray, b2: np.ndarray, h: float, u_lo: np.ndarray, nodes: int):
    """sum_j g(u_lo + j h) over j = 0..nodes-1, for items of step h with all l_i > 0."""
    N, n = lam.shape
    j = np.arange(nodes)
    t = np.exp(u_lo)[:, None] * np.exp(j * h)[None, :]  # (N, nodes)
    # D - 1 = sum_r e_r t^r by Horner's rule, e_r the elementary symmetric polynomials of 2 l_i
    e = np.zeros((N, n + 1))
    e[:, 0] = 1.0
    for i in range(n):
        e[:, 1 : i + 2] += e[:, : i + 1] * (2.0 * lam[:, i : i + 1])
    p = t * e[:, n, None]
    for r in range(n - 1, 0, -1):
        p += e[:, r, None]
        p *= t
    np.minimum(p, 1e300, out=p)  # beyond, 1 - D^-1/2 is 1 to rounding; inf would give inf/inf
    sD = np.sqrt(1.0 + p)
    one_minus = p / (sD * (sD + 1.0))  # 1 - D^-1/2 without cancellation
    if b2.any():
        a = np.zeros_like(t)
        for i in range(n):
            a += t * b2[:, i, None] / (1.0 + t * (2.0 * lam[:, i, None]))
        one_minus += -np.expm1(-a) / sD
    # e^(-u/2) = e^(-u_lo/2) e^(-j h/2): the sum over nodes as one matrix-vector product
    return (one_minus @ np.exp(-0.5 * h * j)) * np.exp(-0.5 * u_lo)


def _tail_sums(
    lam: np.ndarray, b2: np.ndarray, h: float, u_lo: np.ndarray, u_top: np.ndarray
) -> np.ndarray:
    """sum_j g(u_j) over the nodes u_j = u_lo - h, u_lo - 2h, ... and u_top, u_top + h, ...

    Both series are taken in the variable at their first node (t_b = e^(u_lo - h) below,
    z_i = 1 / (2 t_top l_i) above), where every term is small: no power of an eigenvalue
    overflows, however the items are scaled. Arrays are (n, N) here: sums over i add rows.
    """
    lam, b2 = np.ascontiguousarray(lam.T), np.ascontiguousarray(b2.T)
    n, N = lam.shape
    centred = not b2.any()
    # Below: the cumulants of t_b q, k_r = 2^(r-1) (r-1)! sum_i ell_i^(r-1) (ell_i + r beta_i),
    # ell = t_b l, beta = t_b b^2; moments m_r = sum_i C(r-1, i) k_(i+1) m_(r-1-i).
    t_b = np.exp(u_lo - h)
    ell, beta = t_b * lam, t_b * b2
    kappa, prev = [], np.ones_like(ell)  # prev = ell^(r-1)
    for r in range(1, _LOW_TERMS + 1):
        power = prev * ell
        k = power.sum(axis=0) if centred else (prev * (ell + r * beta)).sum(axis=0)
        kappa.append(2.0 ** (r - 1) * factorial(r - 1) * k)
        prev = power
    moments = [np.ones(N)]
    for r in range(1, _LOW_TERMS + 1):
        moments.append(sum(comb(r - 1, i) * kappa[i] * moments[r - 1 - i] for i in range(r)))
    below = sum(
        (-1) ** (r + 1) / (factorial(r) * -np.expm1(-(r - 0.5) * h)) * moments[r]
        for r in range(1, _LOW_TERMS + 1)
    )
    total = below / np.sqrt(t_b)
    # Above: alpha_r t_top^-r = sum_i z_i^r ((-1)^r / (2r) + (-1)^(r+1) b_i^2 / (2 l_i)),
    # beta_r t_top^-r from the exponential's recursion, C t_top^(-n/2) = prod_i z_i^1/2
    # exp(-b_i^2 / (2 l_i)).
    e_top = np.exp(-u_top)
    z = e_top / (2.0 * lam)
    rho = b2 / lam
    alpha, power = [], z
    for r in range(1, _HIGH_TERMS):
        a = power.sum(axis=0) * ((-1) ** r / (2 * r))
        if not centred:
            a = a + ((-1) ** (r + 1) * 0.5) * (power * rho).sum(axis=0)
        alpha.append(a)
        power = power * z
    coef = [np.ones(N)]
    for r in range(1, _HIGH_TERMS):
        coef.append(sum(j * alpha[j - 1] * coef[r - j] for j in range(1, r + 1)) / r)
    lead = np.sqrt(np.prod(z, axis=0))
    if not centred:
        lead *= np.exp(-0.5 * rho.sum(axis=0))
    above = 1.0 / -np.expm1(-0.5 * h) - lead * sum(
        coef[r] / -np.expm1(-((n + 1) / 2 + r) * h) for r in range(_HIGH_TERMS)
    )
    return total + np.sqrt(e_top) * above


def whitening(P: np.ndarray) -> np.ndarray:
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
        return whitening(P * (s[..., :, None] * s[..., None, :])) * s[..., None, :]
    try:
        return np.linalg.inv(np.linalg.cholesky(P))
    except np.linalg.LinAlgError:
        finite = np.isfinite(P).all(axis=(-2, -1))
        w, V = np.linalg.eigh(np.where(finite[..., None, None], P, np.eye(P.shape[-1])))
        pd = finite & (w[..., 0] > 0)
        s = 1.0 / np.sqrt(np.where(pd[..., None], w, 1.0))
        return np.where(pd[..., None, None], s[..., :, None] * mT(V), np.nan)
