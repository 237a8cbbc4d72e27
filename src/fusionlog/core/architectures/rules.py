"""The paper's fusion rules as `definition.Rule`s, each formula written here once: pure functions
of the local filters' matrices P (..., S, n, n) and joint error covariance J (..., S n, S n) at
any batch of instants, runs or history nodes, giving the weights C (..., n, S n) of
x = C [s_1; ...; s_S] and the reported covariance. Every backend applies them as they are: the
plans and their exact analysis (`track_to_track.build_rule`, shared and per run), the one-run
replay path and the EKF/UKF lanes.

* `msc`      Millman's formula assuming independence, eqs. (32)-(34);
* `msc_gmf`  the generalised Millman formula with the exact cross-covariances, eqs. (5)-(7);
* `ci`       covariance intersection (Gustafsson-Hendeby's "safe fusion");
* `avg`      the plain average with the covariance it really has, eq. (4).

They also fuse local filters still in information form (started without a prior, too few
measurements yet: `definition.Architecture.information`; `found` takes what else a rule found,
which the plan records: CI's weights): with `forms` (S,) the locals' forms,
P[..., j, :, :] is local j's information matrix Y_j where forms[j] and its state s_j the
information vector y_j = Y_j x + g_j, J the covariance of the generalised errors g (eq. 35;
g = x - x_hat in mean form, where s_j = x_hat_j). Written with `linalg`'s helpers (`mm`,
`spd_inv`, ...), they run on numpy's routines for a few problems and on the batch kernels (the
lanes layout) for the per-run path's thousands.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache, partial

import numpy as np

from ..fusion import ci_omegas, gmf_weight_matrix
from ..linalg import (
    inv_or_nan,
    mm,
    mT,
    require_finite,
    solve_spd_or_flag,
    spd_inv,
    spd_inv_scaled,
    stack_cols,
    stack_rows,
    sym,
)

#: A Cholesky pivot of J below this times its diagonal entry, or |J^-1 E| |J| beyond
#: GMF_MAX_GROWTH, sends a GMF problem to the least-squares (KKT) solution: the closed form
#: would amplify rounding by about that much, and where J is singular to working precision the
#: weights are not unique (least squares takes the smallest). The paper's example stays at
#: pivots above 1e-3 and growths below 200.
GMF_PIVOT_RTOL = 1e-6
GMF_MAX_GROWTH = 1e6
#: At most this many distinct GMF problems are solved one by one by least squares (beyond, one
#: batched pseudo-inverse: near a singular J it picks other weights, ~1e-10 in the means).
GMF_ONE_BY_ONE = 256


#: The locals' forms (S,) (True: information form), None: all in mean form.
Forms = np.ndarray | None
#: Where a rule puts what else it found (`definition.Rule`).
Found = dict[str, np.ndarray] | None


@lru_cache(maxsize=64)
def signs(info: tuple[bool, ...], n: int) -> np.ndarray:
    """diag(+I for a local in information form, -I in mean form): sigma = sign g, with
    s = D x + sigma (D_j = I in mean form, Y_j in information form)."""
    return np.kron(np.diag([1.0 if i else -1.0 for i in info]), np.eye(n))


def _informed(forms: np.ndarray | None) -> bool:
    return forms is not None and bool(np.any(forms))


def local_infos(P: np.ndarray, forms: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Each local's information matrix Y_j and the map W_j with Y_j x_j = W_j s_j: in mean form
    Y_j = P_j^-1 = W_j; in information form Y_j is the matrix itself and W_j = I."""
    what = "a local filter's covariance"
    if not _informed(forms):
        Y = spd_inv_scaled(P, what=what)
        require_finite(Y, "the local information P_j^-1")
        return Y, Y
    mean = ~np.asarray(forms)
    Y = P.copy(order="K")  # the per-run path's lanes layout kept (also below)
    Y[..., mean, :, :] = spd_inv_scaled(P[..., mean, :, :], what=what)
    require_finite(Y, "the local information P_j^-1")
    W = Y.copy(order="K")
    W[..., ~mean, :, :] = np.eye(P.shape[-1])
    return Y, W


def msc(
    P: np.ndarray, J: np.ndarray | None, criterion: str, forms: Forms = None, found: Found = None
) -> tuple[np.ndarray, np.ndarray]:
    """Millman's formula (33)-(34) in information form: P_f^-1 = sum_j Y_j, C_j = P_f W_j (the
    information vector itself for a local still in information form)."""
    Ys, Ws = local_infos(P, forms)
    Y = Ys[..., 0, :, :]
    for j in range(1, Ys.shape[-3]):
        Y = Y + Ys[..., j, :, :]
    require_finite(Y, "the fused information sum_j P_j^-1")
    Pf = inv_or_nan(Y)  # each problem on its own
    return stack_cols(mm(Pf[..., None, :, :], Ws)), Pf


def _small_mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B for stacks of small matrices, as n elementwise products over the whole stack:
    matmul calls BLAS once per matrix, which for 10^5 2 x 2 products costs ~30 times more."""
    out = A[..., :, :1] * B[..., :1, :]
    for k in range(1, A.shape[-1]):
        out = out + A[..., :, k : k + 1] * B[..., k : k + 1, :]
    return out


def ci(
    P: np.ndarray, J: np.ndarray | None, criterion: str, forms: Forms = None, found: Found = None
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance intersection: P_f^-1 = sum_j w_j Y_j, C_j = w_j P_f W_j, the weights w on the
    simplex minimising `criterion` (`core.ci.ci_omegas`, every problem solved on its own;
    batch + (S,) into `found["omega"]`). A local in information form with too little
    information for a mean still contributes."""
    Ys, Ws = local_infos(P, forms)
    S, n = Ys.shape[-3], Ys.shape[-1]
    om = ci_omegas(Ys, criterion)  # batch + (S,), read in place whatever Ys's layout
    if found is not None:
        found["omega"] = om
    # sum_j w_j Y_j and the weights w_j P W_j written out over j, elementwise over the batch:
    # einsum took ten times longer on the local filters' layout, and matmul calls BLAS once
    # per 2 x 2 matrix.
    Y = om[..., 0, None, None] * Ys[..., 0, :, :]
    for j in range(1, S):
        Y = Y + om[..., j, None, None] * Ys[..., j, :, :]
    Pf = inv_or_nan(Y)
    C = np.empty(Pf.shape[:-1] + (S * n,))
    for j in range(S):
        np.multiply(
            om[..., j, None, None], _small_mm(Pf, Ws[..., j, :, :]), out=C[..., j * n : (j + 1) * n]
        )
    return C, Pf


def avg(
    P: np.ndarray, J: np.ndarray, criterion: str, forms: Forms = None, found: Found = None
) -> tuple[np.ndarray, np.ndarray]:
    """Equal weights on the local means, c_j = I/S (eq. 2), and the covariance they really give,
    C J C^T (eq. 4); a local in information form gives its mean P_j y_j where its information
    is invertible, NaN where it is not."""
    S, n = P.shape[-3], P.shape[-1]
    if not _informed(forms):
        C = np.tile(np.eye(n), (1, S)) / S
        return np.broadcast_to(C, P.shape[:-3] + C.shape), sym(mm(mm(C, J), mT(C)))
    info = np.asarray(forms)
    O = np.empty_like(P)
    O[...] = np.eye(n)
    O[..., info, :, :] = inv_or_nan(P[..., info, :, :])
    C = stack_cols(O) / S
    Msig = mm(C, signs(tuple(info.tolist()), n))
    return C, sym(mm(mm(Msig, J), mT(Msig)))


def msc_gmf(
    P: np.ndarray, J: np.ndarray, criterion: str, forms: Forms = None, found: Found = None
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. (5)-(7): C minimising C Sigma C^T subject to sum_j c_j D_j = I, Sigma the covariance
    of the stacked states' errors. With every local in mean form (D_j = I, Sigma = J) and J
    safely positive definite, the closed form C = (E^T J^-1 E)^-1 E^T J^-1 (E = [I; ...; I]),
    one batched Cholesky; elsewhere (J singular or nearly: locals that share an error, e.g. the
    paper's identical sensors the prior's velocity error until their gains differ; a local in
    information form, D_j = Y_j) the minimum-norm KKT solution `gmf_weight_matrix`, once per
    distinct problem."""
    n = P.shape[-1]
    if _informed(forms):
        info = np.asarray(forms)
        sign = signs(tuple(info.tolist()), n)
        D = P.copy(order="K")
        D[..., ~info, :, :] = np.eye(n)
        return _each_once(partial(_kkt, n), mm(mm(sign, J), sign), stack_rows(D))
    S = J.shape[-1] // n
    E = np.tile(np.eye(n), (S, 1))
    X, ok = solve_spd_or_flag(J, E, GMF_PIVOT_RTOL)  # J^-1 E
    ok &= np.abs(X).max(axis=(-2, -1)) * np.abs(J).max(axis=(-2, -1)) < GMF_MAX_GROWTH
    if not ok.all():
        X[~ok] = E  # placeholders, replaced below
    W = X[..., :n, :]
    for i in range(1, S):
        W = W + X[..., i * n : (i + 1) * n, :]
    C = mm(spd_inv(W), mT(X))
    Pf = sym(mm(mm(C, J), mT(C)))
    ok &= np.isfinite(Pf).all(axis=(-2, -1))  # e.g. subnormal noise variances
    if not ok.all():
        bad = np.nonzero(~ok)
        C[bad], Pf[bad] = _each_once(partial(_kkt, n), J[bad])
    return C, Pf


def _kkt(n: int, J: np.ndarray, D: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`gmf_weight_matrix` for a batch of distinct J (and D), each solved on its own by least
    squares (near a singular J the weights are not unique and the batched pseudo-inverse picks
    other ones, ~1e-10 in the means); many through the batched call."""
    if len(J) > GMF_ONE_BY_ONE:
        return gmf_weight_matrix(J, n, D)
    outs = [gmf_weight_matrix(J[i], n, None if D is None else D[i]) for i in range(len(J))]
    C = np.stack([o[0] for o in outs]) if outs else np.empty(J.shape[:1] + (n, J.shape[-1]))
    P = np.stack([o[1] for o in outs]) if outs else np.empty(J.shape[:1] + (n, n))
    return C, P


def _each_once(
    solve: Callable[..., tuple[np.ndarray, np.ndarray]], *args: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """solve(*args) over a batch (any leading shape), computed once per distinct problem (runs
    with the same measurement history have the same J, to the last bit) and handed to every
    problem that has it."""
    batch = args[0].shape[:-2]
    flat = [np.ascontiguousarray(a).reshape((-1,) + a.shape[-2:]) for a in args]
    rows = np.concatenate([a.reshape(len(a), -1) for a in flat], axis=1)
    keys = rows.view(np.dtype((np.void, rows.shape[1] * 8))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    outs = solve(*(a[first] for a in flat))
    return tuple(o[inverse.ravel()].reshape(batch + o.shape[1:]) for o in outs)
