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

from .linalg import sym
from .model import System

__all__ = ["Innovations", "innovations", "whiteness"]


@dataclass
class Innovations:
    """NIS (M, K+1) (NaN where nothing was measured), its degrees of freedom (M, K+1) and the
    normalised innovations (M, K+1, r) (NaN where absent), for the components `rows` of z."""

    nis: np.ndarray
    dof: np.ndarray
    normalised: np.ndarray


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
    per instant where it varies: `System.R_at`)."""
    M, K1, _ = z.shape
    H = system.H[rows]
    r = len(rows)
    nis = np.full((M, K1), np.nan)
    dof = np.zeros((M, K1), dtype=int)
    out = np.full((M, K1, r), np.nan)
    for k in range(K1):
        if k == 0:
            if system.prior is None:
                continue
            xp = np.broadcast_to(system.prior.mean, (M, system.n))
            Pp = system.prior.cov
        else:
            F, Q = system.F_at(k), system.GQG_at(k)
            xp = mean[:, k - 1] @ F.T
            Pk = cov[k - 1] if cov.ndim == 3 else cov[:, k - 1]
            Pp = sym(F @ Pk @ F.T + Q)
        Rk = system.R_at(k)[np.ix_(rows, rows)] if R is None else R
        zk = z[:, k, rows]
        present = ~np.isnan(zk)  # (M, r)
        if not present.any():
            continue
        ok = np.isfinite(xp).all(axis=-1) & np.isfinite(Pp).all(axis=(-2, -1))
        nu = np.where(present, np.nan_to_num(zk) - xp @ H.T, 0.0)
        S = sym(H @ Pp @ H.T + Rk)
        pf = present.astype(float)
        S = S * (pf[:, :, None] * pf[:, None, :]) + np.eye(r) * (1.0 - pf)[:, None, :]
        try:
            L = np.linalg.cholesky(S)
        except np.linalg.LinAlgError:  # not positive definite for some run: no NIS there
            continue
        u = np.linalg.solve(L, nu[..., None])[..., 0]  # S^-1/2 nu (whitened by Cholesky)
        use = ok & present.any(axis=-1)
        nis[use, k] = (u[use] ** 2).sum(axis=-1)
        dof[use, k] = present[use].sum(axis=-1)
        out[use, k] = np.where(present[use], u[use], np.nan)
    return Innovations(nis, dof, out)


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
