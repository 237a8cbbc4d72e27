"""The paper's fusion rules as `definition.Rule`s: pure functions of the local filters'
covariances P (..., S, n, n) and joint error covariance J (..., S n, S n) at any batch of
instants or runs, giving the weights C (..., n, S n) of x = C [x_1; ...; x_S] and the reported
covariance. The one-run replay path and the EKF/UKF lanes apply them as they are; the plans
keep builders of their own for these four (information-form locals, per-run kernels), which
compute the same formulas (tests/test_replay_fast.py, test_references_nonlinear.py).

* `msc`      Millman's formula assuming independence, eqs. (32)-(34);
* `msc_gmf`  the generalised Millman formula with the exact cross-covariances, eqs. (5)-(7);
* `ci`       covariance intersection (Gustafsson-Hendeby's "safe fusion");
* `avg`      the plain average with the covariance it really has, eq. (4).
"""

from __future__ import annotations

import numpy as np

from ..fusion import gmf_weight_matrix
from ..linalg import solve_spd_or_flag, spd_inv, sym
from .readouts import ci_fusion, msc_fusion
from .track_to_track import GMF_MAX_GROWTH, GMF_ONE_BY_ONE, GMF_PIVOT_RTOL


def _flat(P: np.ndarray) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """The batch shape, P with one batch axis (B, S, n, n) and the locals' forms (B, S) (all
    in mean form: a rule reads covariances)."""
    batch, (S, n) = P.shape[:-3], P.shape[-3:-1]
    flat = P.reshape((-1, S, n, n))
    return batch, flat, np.zeros(flat.shape[:2], dtype=bool)


def msc(P: np.ndarray, J: np.ndarray | None, criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """Millman's formula in information form: P_f^-1 = sum_j P_j^-1, C_j = P_f P_j^-1."""
    batch, flat, forms = _flat(P)
    C, Pf = msc_fusion(forms, flat)
    return C.reshape(batch + C.shape[1:]), Pf.reshape(batch + Pf.shape[1:])


def ci(P: np.ndarray, J: np.ndarray | None, criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection: P_f^-1 = sum_j w_j P_j^-1, C_j = w_j P_f P_j^-1, the weights w
    on the simplex minimising `criterion` (`core.ci.ci_omegas`)."""
    batch, flat, forms = _flat(P)
    C, Pf, _ = ci_fusion(forms, flat, criterion)
    return C.reshape(batch + C.shape[1:]), Pf.reshape(batch + Pf.shape[1:])


def avg(P: np.ndarray, J: np.ndarray, criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """Equal weights C_j = I/S (eq. 2) and the covariance they give, C J C^T (eq. 4)."""
    S, n = P.shape[-3], P.shape[-1]
    C = np.tile(np.eye(n), (1, S)) / S
    return np.broadcast_to(C, P.shape[:-3] + C.shape), sym(C @ J @ C.T)


def msc_gmf(P: np.ndarray, J: np.ndarray, criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. (5)-(7): where J is safely positive definite the closed form C = (E' J^-1 E)^-1
    E' J^-1 (E = [I; ...; I]), one batched Cholesky; elsewhere (J singular or nearly: locals
    that share an error, e.g. the prior's before their first measurements) the minimum-norm
    KKT solution `gmf_weight_matrix` of each J alone, as the shared plans solve it."""
    batch, n = J.shape[:-2], P.shape[-1]
    J = J.reshape((-1,) + J.shape[-2:])
    S = J.shape[-1] // n
    E = np.tile(np.eye(n), (S, 1))
    X, ok = solve_spd_or_flag(J, np.broadcast_to(E, J.shape[:1] + E.shape), GMF_PIVOT_RTOL)
    ok &= np.abs(X).max(axis=(-2, -1)) * np.abs(J).max(axis=(-2, -1)) < GMF_MAX_GROWTH
    X = np.where(ok[:, None, None], X, E)  # placeholders where not ok, replaced below
    W = X[:, :n]
    for i in range(1, S):
        W = W + X[:, i * n : (i + 1) * n]
    C = spd_inv(W) @ X.swapaxes(-1, -2)
    Pf = sym(C @ J @ C.swapaxes(-1, -2))
    ok &= np.isfinite(Pf).all(axis=(-2, -1))
    bad = np.flatnonzero(~ok)
    if len(bad) > GMF_ONE_BY_ONE:
        C[bad], Pf[bad] = gmf_weight_matrix(J[bad], n)
    else:
        for k in bad:
            C[k], Pf[k] = gmf_weight_matrix(J[k], n)
    return C.reshape(batch + C.shape[1:]), Pf.reshape(batch + Pf.shape[1:])
