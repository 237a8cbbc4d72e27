"""ICI, inverse covariance intersection (Noack, Sijs, Reinhardt, Hanebeck 2017, "Decentralized
data fusion with inverse covariance intersection", Automatica 79; DESIGN.md "Unknown correlation
and the bound check"): fusion of estimates whose correlation is unknown, tighter than CI.

For two estimates (x_a, P_a), (x_b, P_b) and a weight w in [0, 1]:

    Gamma = w P_a + (1 - w) P_b,        P^-1 = P_a^-1 + P_b^-1 - Gamma^-1,
    x = P (P_a^-1 - w Gamma^-1) x_a + P (P_b^-1 - (1 - w) Gamma^-1) x_b,

with w minimising tr P. With more than two local filters the pairs are fused in sensor order,
((1 + 2) + 3) + ..., each pair with its own w. The weights depend on covariances only, so the
rule is linear in the data and has the exact analysis like every other.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..linalg import spd_inv, sym
from .definition import Architecture

#: Bisection steps on d tr P / d w: the bracket [0, 1] halves each time, to below rounding.
BISECTIONS = 60
#: d tr P / d w at both ends within this of tr(P_a + P_b): the cost is flat (P_a = P_b, every
#: w gives the same P) and w = 1/2 averages the means, instead of rounding picking an end.
FLAT = 1e-12


def ici_pair(
    Pa: np.ndarray, Pb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One ICI fusion for a batch (..., n, n): the weights A, B of x = A x_a + B x_b, the fused
    P and w. tr P is convex in w; its derivative d tr P / d w = -tr(Gamma^-1 (P_a - P_b)
    Gamma^-1 P^2) is increasing, so w is 0 where it is >= 0 at 0, 1 where it is <= 0 at 1, and
    its root otherwise, found by bisection (every problem on its own, whatever the batch)."""
    Ya = spd_inv(Pa, "a local covariance")
    Yb = spd_inv(Pb, "a local covariance")
    D = Pa - Pb

    def parts(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        wc = w[..., None, None]
        Gi = spd_inv(wc * Pa + (1.0 - wc) * Pb, "ICI's Gamma")
        return Gi, spd_inv(Ya + Yb - Gi, "ICI's fused information")

    def slope(w: np.ndarray) -> np.ndarray:
        Gi, P = parts(w)
        return -np.einsum("...ii->...", Gi @ D @ Gi @ (P @ P))

    batch = Pa.shape[:-2]
    lo, hi = np.zeros(batch), np.ones(batch)
    g0, g1 = slope(lo), slope(hi)
    scale = np.einsum("...ii->...", Pa + Pb)
    w = np.where(g0 >= 0, 0.0, np.where(g1 <= 0, 1.0, np.nan))
    w = np.where((np.abs(g0) <= FLAT * scale) & (np.abs(g1) <= FLAT * scale), 0.5, w)
    inner = np.isnan(w)
    if inner.any():
        w[inner] = ici_bisect(Pa[inner], Pb[inner], Ya[inner], Yb[inner])
    Gi, P = parts(w)
    wc = w[..., None, None]
    return P @ (Ya - wc * Gi), P @ (Yb - (1.0 - wc) * Gi), sym(P), w


def ici_bisect(Pa: np.ndarray, Pb: np.ndarray, Ya: np.ndarray, Yb: np.ndarray) -> np.ndarray:
    """The root of d tr P / d w in (0, 1) for problems (B, n, n) whose slope changes sign."""
    D = Pa - Pb
    lo, hi = np.zeros(len(Pa)), np.ones(len(Pa))
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        wc = mid[:, None, None]
        Gi = spd_inv(wc * Pa + (1.0 - wc) * Pb, "ICI's Gamma")
        P = spd_inv(Ya + Yb - Gi, "ICI's fused information")
        up = -np.einsum("...ii->...", Gi @ D @ Gi @ (P @ P)) > 0
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    return 0.5 * (lo + hi)


def in_sensor_order(P: np.ndarray, pair: Callable) -> tuple[np.ndarray, np.ndarray]:
    """The locals (..., S, n, n) fused pairwise in sensor order, ((1 + 2) + 3) + ..., by
    `pair(P_a, P_b) -> (A, B, P, ...)` (x = A x_a + B x_b): C (..., n, S n) composes each
    pair's weights (the running fusion's A, the next local's B); returns C and the fused P."""
    S, n = P.shape[-3], P.shape[-1]
    C = np.zeros(P.shape[:-3] + (n, S * n))
    C[..., :, :n] = np.eye(n)
    Pf = P[..., 0, :, :]
    for j in range(1, S):
        A, B, Pf = pair(Pf, P[..., j, :, :])[:3]
        C = A @ C
        C[..., :, j * n : (j + 1) * n] = B
    return C, Pf


def ici(P: np.ndarray, J: np.ndarray | None, criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """The rule (`definition.Rule`): the locals (..., S, n, n) fused pairwise in sensor order
    (`in_sensor_order`). tr P is ICI's cost whatever `criterion` (covariance intersection's)
    says."""
    return in_sensor_order(P, ici_pair)


ICI = Architecture(
    "ICI",
    "local KFs, inverse covariance intersection in sensor order (Noack et al. 2017)",
    "per-sensor",
    rule=ici,
    min_sensors=2,
    color=(0, 128, 128),
)
