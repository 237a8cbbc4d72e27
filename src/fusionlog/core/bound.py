"""The bound check (DESIGN.md "Unknown correlation and the bound check"): does the covariance an
architecture reports bound its true error?

A reported P bounds the error's second moment E[e e^T] (bias included) when P - E[e e^T] is
positive semidefinite, i.e. when every eigenvalue of P^-1 E[e e^T] is at most 1. The largest,

    lambda_k = lambda_max(P_k^-1 E[e_k e_k^T]) = lambda_max(W_k E[e_k e_k^T] W_k^T),

W_k^T W_k = P_k^-1 (the whitening), is the factor by which P_k would have to grow to bound the
error in every direction; its trace counterpart is the expected NEES. With the exact analysis
(`exact.Expected`) lambda_k is exact at each instant (per run where the measurement patterns
differ: the worst over the runs, `exact.ConditionalExpected`). Without one (EKF/UKF local
filters) `BoundSums` estimates the same ratio by Monte Carlo: lambda_max of the run average of
u u^T, u = W e the error whitened by each run's own P (equal to the exact ratio where P is
shared by the runs), with a standard error by the delta method.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .linalg import sym
from .quadratic_form import whitening

__all__ = ["BOUND_TOL", "BoundSums", "bound_ratio", "bound_summary"]

#: The bound holds when the worst ratio is at most 1 + BOUND_TOL (rounding of the exact analysis).
BOUND_TOL = 1e-9


def bound_ratio(P: np.ndarray, mse: np.ndarray) -> np.ndarray:
    """lambda_max(P^-1 mse) of a batch (..., n, n) -> (...); NaN where P is undefined (an
    architecture without an estimate yet) or not positive definite."""
    out = np.full(P.shape[:-2], np.nan)
    ok = np.isfinite(P).all(axis=(-2, -1)) & np.isfinite(mse).all(axis=(-2, -1))
    if ok.any():
        W = whitening(P[ok])
        good = np.isfinite(W).all(axis=(-2, -1))
        lam = np.full(len(W), np.nan)
        if good.any():
            Wg = W[good]
            lam[good] = np.linalg.eigvalsh(sym(Wg @ mse[ok][good] @ np.swapaxes(Wg, -1, -2)))[
                ..., -1
            ]
        out[ok] = lam
    return out


def bound_summary(
    ratio: np.ndarray, stderr: np.ndarray | None = None, confidence: float = 0.95
) -> dict[str, Any] | None:
    """summary.json's ``bound`` of a ratio per instant (K+1,) (NaN: no estimate there):
    {"holds", "worst", "worst_step"} (the first instant within BOUND_TOL of the worst); None
    when no instant has one.

    Exact (`stderr` None): holds = worst <= 1 + BOUND_TOL. A Monte Carlo estimate (`stderr`
    per instant) adds ``"monte_carlo": true`` and the worst instant's ``stderr``, and holds
    unless some instant exceeds 1 by more than its uncertainty allows: lambda_k > 1 + z se_k,
    z the normal quantile of a one-sided test at `confidence` over all instants together
    (Bonferroni: 1 - (1 - confidence)/(instants tested))."""
    r = np.asarray(ratio, dtype=float)
    ok = np.isfinite(r)
    if stderr is not None:
        ok &= np.isfinite(stderr)
    if not ok.any():
        return None
    worst = float(r[ok].max())
    # the first instant within rounding of the worst: where the ratio is flat (a consistent
    # filter's 1 at every instant) rounding would otherwise pick the instant
    k = int(np.flatnonzero(ok & (r >= worst - BOUND_TOL * max(abs(worst), 1.0)))[0])
    if stderr is None:
        return {"holds": bool(worst <= 1.0 + BOUND_TOL), "worst": worst, "worst_step": k}
    from scipy.special import ndtri  # an evaluation's only

    z = float(ndtri(1.0 - (1.0 - confidence) / int(ok.sum())))
    holds = bool(np.all(r[ok] <= 1.0 + z * stderr[ok]))
    return {
        "holds": holds,
        "worst": worst,
        "worst_step": k,
        "monte_carlo": True,
        "stderr": float(stderr[k]),
    }


@dataclass
class BoundSums:
    """Monte Carlo sums of the whitened error u = W e per instant (module docstring), over
    blocks of runs: sum u u^T (K+1, n, n) and, for the standard error, the sum of q q^T
    (K+1, p, p) with q the p = n(n+1)/2 distinct products u_i u_j (i <= j)."""

    n_steps: int
    n_states: int
    count: np.ndarray = field(init=False)
    second: np.ndarray = field(init=False)
    fourth: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        n = self.n_states
        p = n * (n + 1) // 2
        self.count = np.zeros(self.n_steps, dtype=np.int64)
        self.second = np.zeros((self.n_steps, n, n))
        self.fourth = np.zeros((self.n_steps, p, p))

    def add(self, truth: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> None:
        """A block: truth and mean (runs, K+1, n), cov (K+1, n, n) shared or per run; a run
        and instant without an estimate (or a covariance not positive definite) is left out."""
        W = whitening(np.where(np.isfinite(cov), cov, np.nan))
        e = truth - mean
        u = (W @ e[..., None])[..., 0] if W.ndim == 4 else np.einsum("kij,rkj->rki", W, e)
        ok = np.isfinite(u).all(axis=-1)
        u = np.where(ok[..., None], u, 0.0)
        iu = np.triu_indices(self.n_states)
        q = u[..., :, None] * u[..., None, :]
        self.count += ok.sum(axis=0)
        self.second += q.sum(axis=0)
        qp = q[..., iu[0], iu[1]]
        self.fourth += np.einsum("rki,rkj->kij", qp, qp)

    def merge(self, other: BoundSums) -> BoundSums:
        """Add another block's sums; returns self."""
        self.count += other.count
        self.second += other.second
        self.fourth += other.fourth
        return self

    def ratio(self) -> tuple[np.ndarray, np.ndarray]:
        """(lambda_k, its standard error) per instant, NaN where fewer than two runs have an
        estimate. With v the top eigenvector of the average M of u u^T, lambda = v^T M v is the
        run average of (v^T u)^2 = a^T q (a_ij = v_i v_j, doubled off the diagonal), whose
        variance a^T E[q q^T] a - lambda^2 over the runs gives the standard error (the delta
        method: lambda_max's derivative in M is v v^T)."""
        c = self.count.astype(float)
        good = c >= 2
        lam = np.full(self.n_steps, np.nan)
        se = np.full(self.n_steps, np.nan)
        if not good.any():
            return lam, se
        M = self.second[good] / c[good, None, None]
        w, V = np.linalg.eigh(sym(M))
        v = V[..., -1]
        iu = np.triu_indices(self.n_states)
        a = v[:, iu[0]] * v[:, iu[1]] * np.where(iu[0] == iu[1], 1.0, 2.0)
        m4 = np.einsum("bi,bij,bj->b", a, self.fourth[good], a) / c[good]
        lam[good] = w[..., -1]
        se[good] = np.sqrt(np.maximum(m4 - w[..., -1] ** 2, 0.0) / c[good])
        return lam, se
