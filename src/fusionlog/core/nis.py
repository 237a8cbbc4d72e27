"""Truth-free consistency: the normalised innovation squared (NIS) and innovation whiteness.

For a Kalman filter with filtered estimates x_{k-1}, P_{k-1} the innovation of the measurement
components present at instant k is (eqs. 14-17)

    nu_k = z_k - H x_k^-,   x_k^- = F_k x_{k-1},   P_k^- = F_k P_{k-1} F_k' + Q_k,
    S_k  = H P_k^- H' + R_k,

and for a consistent filter NIS_k = nu_k' S_k^-1 nu_k is chi-square with dim(nu_k) degrees of
freedom, and the normalised innovations S_k^-1/2 nu_k are white (uncorrelated over time). Both
need no ground truth: they are what a recorded log without one can check. At k = 0 the
prediction is the prior (none without a prior: no NIS there).

Absent components (NaN in z) are left out: their rows of nu are zeroed and S gets a unit
diagonal there, which adds nothing to the quadratic form and makes the degrees of freedom the
count of present components.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .linalg import mT, overflow_is_inf, sym
from .model import System
from .nonlinear.local import predict

__all__ = [
    "Innovations",
    "WhitenessSums",
    "innovations",
    "innovations_of",
    "ljung_box",
    "whiteness",
]


@dataclass
class Innovations:
    """NIS (M, K+1) (NaN where nothing was measured), its degrees of freedom (M, K+1) and the
    normalised innovations (M, K+1, r) (NaN where absent), for the components `rows` of z."""

    nis: np.ndarray
    dof: np.ndarray
    normalised: np.ndarray


#: Instants per block of `innovations`: its temporaries (predicted covariances, S, Cholesky
#: factors) are a block's, so that a log of 10^6 instants needs no 10^6 x n x n arrays.
BLOCK = 32_768


def innovations(
    system: System,
    mean: np.ndarray,
    cov: np.ndarray,
    z: np.ndarray,
    rows: np.ndarray,
    R: np.ndarray | None = None,
) -> Innovations:
    """The innovations of a filter whose filtered estimates are mean (M, K+1, n) and cov
    ((K+1, n, n) shared or (M, K+1, n, n)), on the components `rows` of the stacked
    measurements z (M, K+1, m), with noise covariance R (rows x rows; default the system's,
    per instant where it varies: `System.R_at`). Computed in blocks of `BLOCK` instants."""
    return innovations_of(system, mean, cov, z, [rows], R)[0]


@overflow_is_inf  # an outlier near 1e308: its NIS is inf, reported as non-finite
def innovations_of(
    system: System,
    mean: np.ndarray,
    cov: np.ndarray,
    z: np.ndarray,
    parts: list[np.ndarray],
    R: np.ndarray | None = None,
) -> list[Innovations]:
    """`innovations` of one filter's estimates on each of the components `parts` (one sensor's
    rows each), block by block: a linear model's predictions x_k^-, P_k^- of a block made once
    for all the parts (they depend on the estimates only)."""
    M, K1, _ = z.shape
    out = []
    for rows in parts:
        r = len(rows)
        out.append((np.full((M, K1), np.nan), np.zeros((M, K1), dtype=np.int64),
                    np.full((M, K1, r), np.nan)))  # fmt: skip
    for k0 in range(0, K1, BLOCK):
        k1 = min(K1, k0 + BLOCK)
        predicted = _predicted(system, mean, cov, k0, k1) if system.linear else None
        for rows, (nis, dof, normalised) in zip(parts, out, strict=True):
            got = _block(system, mean, cov, z, rows, R, k0, k1, predicted)
            nis[:, k0:k1], dof[:, k0:k1], normalised[:, k0:k1] = got
    return [Innovations(*o) for o in out]


def _block(system, mean, cov, z, rows, R, k0: int, k1: int, predicted=None):
    """NIS, degrees of freedom and normalised innovations of the instants k0..k1-1
    (`predicted`: a linear model's predictions there, `_predicted`)."""
    if not system.linear:
        return _extended_block(system, mean, cov, z, rows, R, k0, k1)
    H = system.linear_measurement()[rows]
    xp, Pp = predicted if predicted is not None else _predicted(system, mean, cov, k0, k1)
    S = sym(H @ Pp @ H.T + _noise(system, rows, R, k0, k1))  # ([M,] w, r, r)
    zr = z[:, k0:k1][:, :, rows]
    present = ~np.isnan(zr)  # (M, w, r)
    usable = np.isfinite(xp).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
    nu = np.where(present, np.nan_to_num(zr) - xp @ H.T, 0.0)
    return _normalised(nu, S, present, usable)


def _predicted(system: System, mean: np.ndarray, cov: np.ndarray, k0: int, k1: int):
    """A linear model's predictions at the instants k0..k1-1, (M, w, n) and ([M,] w, n, n):
    x_k^- = F_k x_{k-1}, P_k^- = F_k P F_k' + Q_k (k >= 1), the prior at k = 0 (none
    without a prior), from the filtered estimates of the instants before."""
    M, n, w = mean.shape[0], system.n, k1 - k0
    a = max(k0, 1)  # the first instant with a predecessor
    xp = np.full((M, w, n), np.nan)
    Pp = np.full(cov.shape[:-3] + (w, n, n), np.nan)
    xp[:, a - k0 :], Pp[..., a - k0 :, :, :] = _linear_prediction(
        system, mean[:, a - 1 : k1 - 1], cov[..., a - 1 : k1 - 1, :, :], a, k1
    )
    _prior(system, xp, Pp, k0)
    return xp, Pp


def _normalised(nu: np.ndarray, S: np.ndarray, present: np.ndarray, usable: np.ndarray):
    """NIS, degrees of freedom and S^-1/2 nu of innovations nu ([M,] w, r) (zero where absent)
    with covariances S, the components `present` (M, w, r), at the instants `usable` (M, w)."""
    r = nu.shape[-1]
    pf = present.astype(float)
    S = np.where(np.isfinite(S), S, np.eye(r))
    S = S * (pf[..., :, None] * pf[..., None, :]) + np.eye(r) * (1.0 - pf)[..., None, :]
    S = np.where(usable[..., None, None], S, np.eye(r))
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:  # some S not positive definite: no NIS there
        usable &= np.linalg.eigvalsh(S)[..., 0] > 0
        L = np.linalg.cholesky(np.where(usable[..., None, None], S, np.eye(r)))
    u = np.linalg.solve(L, nu[..., None])[..., 0]  # S^-1/2 nu (whitened by Cholesky)
    use = usable & present.any(axis=-1)
    nis = np.where(use, (u**2).sum(axis=-1), np.nan)
    dof = np.where(use, present.sum(axis=-1), 0)
    return nis, dof, np.where(use[..., None] & present, u, np.nan)


def _linear_prediction(system: System, mean: np.ndarray, cov: np.ndarray, a: int, k1: int):
    """x_k^- = F_k x_{k-1}, P_k^- = F_k P_{k-1} F_k' + Q_k for k = a..k1-1 from the estimates
    mean (M, k1-a, n) and cov ([M,] k1-a, n, n) of the instants before them."""
    F, Q = system.transitions(a - 1, k1 - 1)
    xp = np.einsum("kij,mkj->mki", F, mean)
    if system.time_invariant and cov.ndim == 3 and len(cov) > 1:
        # a steady filter's shared covariance repeats the same matrix instant after instant
        # (a long log's blocks): each stretch of one matrix predicted once, the same values
        same = (cov[1:] == cov[:-1]) & (np.signbit(cov[1:]) == np.signbit(cov[:-1]))
        first = np.flatnonzero(np.r_[True, ~same.all(axis=(1, 2))])
        if len(first) < len(cov) // 2:
            u = len(first)
            Pp = sym(F[:u] @ cov[first] @ mT(F[:u]) + Q[:u])
            return xp, np.repeat(Pp, np.diff(np.r_[first, len(cov)]), axis=0)
    return xp, sym(F @ cov @ mT(F) + Q)


def _prior(system: System, xp: np.ndarray, Pp: np.ndarray, k0: int) -> None:
    """The prediction at k = 0 is the prior (none without one: NaN stays)."""
    if k0 == 0 and system.prior is not None:
        xp[:, 0] = system.prior.mean
        Pp[..., 0, :, :] = system.prior.cov


def _noise(system: System, rows: np.ndarray, R: np.ndarray | None, k0: int, k1: int):
    """R of the components `rows` at the instants k0..k1-1: `R` when given, else the system's
    (per instant where it varies)."""
    if R is not None:
        return R
    if system.Rs is None:
        return system.R[np.ix_(rows, rows)]
    return system.Rs[k0:k1][:, rows][:, :, rows]


def _extended_block(system, mean, cov, z, rows, R, k0: int, k1: int):
    """`_block` of a nonlinear model: the EKF's innovation (Bar-Shalom, Li and Kirubarajan
    2001, sec. 10.3), nu_k = z_k - h(x_k^-), x_k^- = f(x_{k-1}), P_k^- = F_J P_{k-1} F_J' + Q_k,
    S_k = H_k P_k^- H_k' + R_k, with F_J and H_k the motion's and the sensors' Jacobians at
    x_{k-1} and at x_k^- (the lanes' own `local.predict` and the sensor models' h, jacobian
    and residual: bearings wrapped to (-pi, pi]). For a UKF's estimates this is the same
    EKF-form innovation of its estimates (the unscented one differs by the curvature the
    linearisation leaves out, small where the filter's covariance is)."""
    M, n, w = z.shape[0], system.n, k1 - k0
    cov = np.broadcast_to(cov, (M,) + cov.shape[-3:])
    a = max(k0, 1)
    xp, Pp = np.full((M, w, n), np.nan), np.full((M, w, n, n), np.nan)
    x0, P0 = mean[:, a - 1 : k1 - 1], cov[:, a - 1 : k1 - 1]
    with np.errstate(all="ignore"):  # a state on a sensor (r = 0) or overflow: no NIS there
        if system.motion_model is None:  # linear motion, nonlinear sensors
            xp[:, a - k0 :], Pp[:, a - k0 :] = _linear_prediction(system, x0, P0, a, k1)
        else:
            dts = np.array([system.dt_at(k) for k in range(a, k1)])
            for dt in np.unique(dts):  # one interval on regular instants
                at = np.flatnonzero(dts == dt)
                x, P = x0[:, at].reshape(-1, n), P0[:, at].reshape(-1, n, n)
                xq, Pq = predict(system.motion_model, float(dt), x, P, None)[:2]
                xp[:, a - k0 + at] = xq.reshape(M, len(at), n)
                Pp[:, a - k0 + at] = Pq.reshape(M, len(at), n, n)
        _prior(system, xp, Pp, k0)
        H = system.jacobian(xp)[..., rows, :]  # (M, w, r, n)
        S = sym(H @ Pp @ mT(H) + _noise(system, rows, R, k0, k1))
        zr = z[:, k0:k1][:, :, rows]
        present = ~np.isnan(zr)
        full = np.where(np.isnan(z[:, k0:k1]), 0.0, z[:, k0:k1])
        nu = np.where(present, system.residual(full, system.h(xp))[..., rows], 0.0)
    usable = np.isfinite(xp).all(axis=-1) & np.isfinite(S).all(axis=(-2, -1))
    usable &= np.isfinite(nu).all(axis=-1)
    return _normalised(np.where(usable[..., None], nu, 0.0), S, present, usable)


@overflow_is_inf
def whiteness(normalised: np.ndarray, lags: int = 10) -> dict[str, float]:
    """Sample autocorrelation of each normalised-innovation component at lags 1..L, averaged
    over the runs' sequences of present values, against the white-noise band +-1.96/sqrt(N).

    Returns the lags, the largest |rho| found, the band, and the share of (component, lag)
    pairs inside it (about 0.95 for a consistent filter)."""
    M, K1, r = normalised.shape
    rhos: list[float] = []
    n_min = K1
    for i in range(r):
        for m in range(M):
            seq = normalised[m, :, i]
            seq = seq[np.isfinite(seq)]
            if len(seq) < lags + 2:
                continue
            n_min = min(n_min, len(seq))
            seq = seq - seq.mean()
            den = float(seq @ seq)
            if den <= 0:
                continue
            rhos += [float(seq[:-lag] @ seq[lag:]) / den for lag in range(1, lags + 1)]
    return _whiteness(rhos, n_min, lags)


def _whiteness(rhos: list[float], n_min: int | None, lags: int) -> dict[str, float]:
    """`whiteness`'s record of the autocorrelations `rhos` of sequences of `n_min` values or
    more: the largest |rho|, the band +-1.96/sqrt(n_min), the share inside it."""
    if not rhos:
        return {"lags": lags, "max_abs_autocorr": float("nan"), "bound": float("nan"),
                "fraction_inside": float("nan")}  # fmt: skip
    bound = 1.96 / np.sqrt(n_min)
    a = np.abs(np.array(rhos))
    return {
        "lags": lags,
        "max_abs_autocorr": float(a.max()),
        "bound": float(bound),
        "fraction_inside": float((a <= bound).mean()),
    }


#: The Ljung-Box test's lag when the sequences are long enough (the usual choice for daily
#: and sensor series alike; shorter sequences take a quarter of their length).
LJUNG_BOX_LAGS = 20


def ljung_box(normalised: np.ndarray, lags: int = LJUNG_BOX_LAGS) -> dict[str, float]:
    """The Ljung-Box portmanteau test (Ljung and Box 1978) of normalised innovations
    (M, K+1, r) (NaN: absent): for each run's sequence of present values of each component,
    Q = N (N + 2) sum_{h=1..L} rho_h^2 / (N - h), chi-square with L degrees of freedom when
    the sequence is white, rho_h the autocorrelation about zero (the innovations' mean under
    the hypothesis: a sample mean would bias every rho_h by -1/N, which summed over many
    short runs rejects a consistent filter); the sequences' Q are summed (independent runs
    and, for a consistent filter, uncorrelated components), with L degrees of freedom each.
    L = `lags`, or a quarter of the shortest sequence when that is less. Returns the lag, Q,
    the degrees of freedom and the p-value (chi-square survival function): a small p says
    the innovations are not white (the noise model misses something, e.g. a drift)."""
    from scipy.stats import chi2

    M, K1, r = normalised.shape
    # each (run, component) sequence's present values moved to its front, zeros after them:
    # the padding adds nothing to the lagged products
    seqs = np.moveaxis(normalised, 2, 1).reshape(M * r, K1)
    present = np.isfinite(seqs)
    N = present.sum(axis=1)
    keep = N >= 8
    seqs, present, N = seqs[keep], present[keep], N[keep]
    if not len(N):
        return {"lags": 0, "q": float("nan"), "dof": 0, "p": float("nan")}
    order = np.argsort(~present, axis=1, kind="stable")
    packed = np.where(np.take_along_axis(present, order, 1), np.take_along_axis(seqs, order, 1), 0)
    L = max(1, min(lags, int(N.min()) // 4))
    den = (packed**2).sum(axis=1)
    use = den > 0
    q = 0.0
    for h in range(1, L + 1):
        rho = (packed[use, :-h] * packed[use, h:]).sum(axis=1) / den[use]
        q += float((N[use] * (N[use] + 2) * rho**2 / (N[use] - h)).sum())
    dof = L * int(len(N))
    return {"lags": L, "q": q, "dof": dof, "p": float(chi2.sf(q, dof))}


class WhitenessSums:
    """`whiteness` of one run's normalised innovations (w, r) handed over block by block (a
    long log in blocks of time): per component the sums that the autocorrelation about the
    sequence's mean expands into, sum_i (a_i - mu)(a_{i+l} - mu) = C_l - mu (S - tail_l)
    - mu (S - head_l) + (N - l) mu^2 with C_l = sum_i a_i a_{i+l}, S = sum a, head_l / tail_l
    the sums of the first / last l values; the last `lags` values carried into the next block
    for the products that straddle it."""

    def __init__(self, r: int, lags: int = 10) -> None:
        self.lags = lags
        self.N = np.zeros(r, dtype=np.int64)
        self.S = np.zeros(r)
        self.S2 = np.zeros(r)
        self.C = np.zeros((r, lags))
        self.head: list[np.ndarray] = [np.zeros(0)] * r
        self.tail: list[np.ndarray] = [np.zeros(0)] * r

    def add(self, normalised: np.ndarray) -> None:
        L = self.lags
        for i in range(normalised.shape[-1]):
            seq = normalised[:, i]
            seq = seq[np.isfinite(seq)]
            if not len(seq):
                continue
            ext = np.concatenate([self.tail[i], seq])
            t = len(self.tail[i])
            for lag in range(1, L + 1):  # the products a_j a_{j+lag} with j + lag in this block
                lo = max(t - lag, 0)
                # no pair yet (fewer than lag + 1 values so far): ext[lo : negative] would
                # count from the end
                hi = max(len(ext) - lag, lo)
                self.C[i, lag - 1] += float(ext[lo:hi] @ ext[lo + lag : hi + lag])
            self.N[i] += len(seq)
            self.S[i] += float(seq.sum())
            self.S2[i] += float(seq @ seq)
            if len(self.head[i]) < L:
                self.head[i] = np.concatenate([self.head[i], seq])[:L]
            self.tail[i] = ext[-L:]

    def result(self) -> dict[str, float]:
        """What `whiteness` gives of the whole sequences."""
        L, rhos, n_min = self.lags, [], None
        for i in range(len(self.N)):
            N = int(self.N[i])
            if N < L + 2:
                continue
            n_min = N if n_min is None else min(n_min, N)
            mu = self.S[i] / N
            den = self.S2[i] - N * mu * mu
            if den <= 0:
                continue
            for lag in range(1, L + 1):
                num = (
                    self.C[i, lag - 1]
                    - mu * (self.S[i] - self.tail[i][L - lag :].sum())
                    - mu * (self.S[i] - self.head[i][:lag].sum())
                    + (N - lag) * mu * mu
                )
                rhos.append(num / den)
        return _whiteness(rhos, n_min, L)
