"""EI, ellipsoidal intersection (Sijs and Lazar 2012, "State fusion with unknown correlation:
Ellipsoidal intersection", Automatica 48(8); DESIGN.md "Unknown correlation and the bound
check"): fusion of estimates whose correlation is unknown, by removing their *mutual* estimate
(gamma, Gamma) once from the sum of their informations.

For two estimates (x_a, P_a), (x_b, P_b), with the eigen-decompositions (eq. 12)

    P_a = S_a D_a S_a^T,   D_a^-1/2 S_a^T P_b S_a D_a^-1/2 = S_b D_b S_b^T,   T = S_a D_a^1/2 S_b,

T^-1 P_a T^-T = I and T^-1 P_b T^-T = D_b = diag(d_i). The mutual covariance (eq. 11, Theorem 6)
is Gamma = T D_Gamma T^T with D_Gamma = diag(max(d_i, 1)); the fused covariance (eq. 8)
P = (P_a^-1 + P_b^-1 - Gamma^-1)^-1; the mutual mean (eq. 16) in the coordinates mu = T^-1 x,

    mu_gamma = (W_a + W_b)^-1 (W_a mu_a + W_b mu_b),
    W_a = D_b^-1 - D_Gamma^-1 + eta I,   W_b = I - D_Gamma^-1 + eta I,

with eta = 0 when |1 - d_i| > 10 zeta for every i, else eta = zeta (0 < zeta << 1: a direction
where both estimates are equally good has W_a = W_b = 0 and the mutual mean there is their
average), and x = P (P_a^-1 x_a + P_b^-1 x_b - Gamma^-1 gamma), gamma = T mu_gamma (eq. 7).

Everything but the means is a function of the covariances, so x = A x_a + B x_b with A, B from
the covariances alone: the rule is linear in the data and has the exact analysis like every
other. In the coordinates mu every matrix is diagonal: A = T diag(f_a) T^-1, B = T diag(f_b)
T^-1 with p_i = 1/(1 + 1/d_i - 1/dG_i), f_a = p (1 - m_a/dG), f_b = p (1/d - m_b/dG), m_a,b
the weights of mu_gamma; T^-1 = S_b^T D_a^-1/2 S_a^T (no inverse). With more than two local
filters the pairs are fused in sensor order, ((1 + 2) + 3) + ...
"""

from __future__ import annotations

import numpy as np

from ..linalg import mT, sym
from .definition import Architecture
from .ici import in_sensor_order

#: Sijs and Lazar's zeta (eq. 16c), in the coordinates where P_a = I (dimensionless): eta = zeta
#: where some d_i is within 10 zeta of 1. There the split of the mutual mean is decided by
#: (1/d_i - 1/max(d_i, 1) + zeta) against (1 - 1/max(d_i, 1) + zeta), so rounding e in d_i moves
#: it by about e/zeta: far above the rounding of d (1e-15 for well-conditioned P), far below 1.
ZETA = 1e-8


def ei_pair(
    Pa: np.ndarray, Pb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One EI fusion for a batch (..., n, n): the weights A, B of x = A x_a + B x_b, the fused
    P and the mutual covariance Gamma (module docstring)."""
    da, Sa = np.linalg.eigh(sym(Pa))
    ra = np.sqrt(da)
    L = Sa / ra[..., None, :]  # S_a D_a^-1/2
    d, Sb = np.linalg.eigh(sym(mT(L) @ Pb @ L))
    T = (Sa * ra[..., None, :]) @ Sb  # S_a D_a^1/2 S_b
    Tinv = mT(L @ Sb)  # S_b^T D_a^-1/2 S_a^T
    dG = np.maximum(d, 1.0)
    near = (np.abs(1.0 - d) <= 10.0 * ZETA).any(axis=-1, keepdims=True)
    eta = np.where(near, ZETA, 0.0)
    wa = 1.0 / d - 1.0 / dG + eta
    wb = 1.0 - 1.0 / dG + eta
    ma, mb = wa / (wa + wb), wb / (wa + wb)
    p = 1.0 / (1.0 + 1.0 / d - 1.0 / dG)
    fa = p * (1.0 - ma / dG)
    fb = p * (1.0 / d - mb / dG)
    A = (T * fa[..., None, :]) @ Tinv
    B = (T * fb[..., None, :]) @ Tinv
    P = sym((T * p[..., None, :]) @ mT(T))
    Gamma = sym((T * dG[..., None, :]) @ mT(T))
    return A, B, P, Gamma


def ei(P: np.ndarray, J: np.ndarray | None, criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """The rule (`definition.Rule`): the locals (..., S, n, n) fused pairwise in sensor order
    (`ici.in_sensor_order`). EI has no cost to minimise: `criterion` (covariance
    intersection's) does not apply."""
    return in_sensor_order(P, ei_pair)


EI = Architecture(
    "EI",
    "local KFs, ellipsoidal intersection in sensor order (Sijs and Lazar 2012)",
    "per-sensor",
    rule=ei,
    min_sensors=2,
    color=(188, 189, 34),
)
