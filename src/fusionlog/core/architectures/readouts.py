"""The fusion rules of track-to-track fusion as plan readouts x_hat = O s, P (see
`track_to_track`), evaluated for all computed steps of the local filters together.

The fused state s stacks the locals' states s_j: a local in covariance form carries its mean
x_j (s_j = x + sigma_j, sigma_j = -g_j with g_j = x - x_j), one still in information form its
information vector y_j = Y_j x + g_j. `signs` maps the joint error covariance J = cov(g) of
eq. (35) to cov(sigma).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ...errors import NumericalError
from ..fusion import ci_omegas, gmf_weight_matrix
from ..linalg import all_finite, bc, inv_or_nan, mT, require_finite, spd_inv_scaled, stack_cols, sym
from .plan import StepMap


def require_fused(forms: np.ndarray, P: np.ndarray, rule: str) -> None:
    """Refuse a fused covariance P ((L,) + batch + (n, n)) that is undefined at a step where
    every local filter has an estimate of its own (forms (L, S) all False): the rule has an
    answer there, so NaN means its numbers left the float range."""
    if all_finite(P):
        return
    every = ~forms.any(axis=1)
    bad = every & ~np.isfinite(P).reshape(len(P), -1).all(axis=1)
    if bad.any():
        raise NumericalError(
            f"step {int(np.argmax(bad))}: {rule} gives no estimate although every local filter "
            "has one (their informations are beyond the float range)"
        )


def set_readouts(steps: list[StepMap], O: np.ndarray, P: np.ndarray) -> None:
    """Readout O and reported covariance P of each step from arrays over the steps (L, ...)."""
    for i, st in enumerate(steps):
        st.O, st.P = O[i], P[i]


@lru_cache(maxsize=64)
def signs(info: tuple[bool, ...], n: int) -> np.ndarray:
    """diag(+I for a local in information form, -I in mean form): sigma = sign g."""
    return np.kron(np.diag([1.0 if i else -1.0 for i in info]), np.eye(n))


def local_infos(forms: np.ndarray, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each local's information matrix Y_j and the map W_j with Y_j x_j = W_j s_j, for L steps
    at once: forms (L, S), mats (L,) + batch + (S, n, n). In covariance form Y_j = P_j^-1 = W_j;
    in information form the state is the information vector itself: Y_j is the matrix the
    filter carries and W_j = I."""
    what = "a local filter's covariance"
    if not forms.any():
        Y = spd_inv_scaled(mats, what=what)
        require_finite(Y, "the local information P_j^-1", per_step=True)
        return Y, Y
    # Steps and locals side by side, (L, S) + batch + (n, n), to pick them by their form.
    M = np.moveaxis(mats, -3, 1)
    Y = np.empty_like(M)
    Y[~forms] = spd_inv_scaled(M[~forms], what=what)
    Y[forms] = M[forms]
    require_finite(Y, "the local information P_j^-1", per_step=True)
    W = Y.copy()
    W[forms] = np.eye(mats.shape[-1])
    return np.moveaxis(Y, 1, -3), np.moveaxis(W, 1, -3)


def msc_readouts(steps: list[StepMap], forms: np.ndarray, mats: np.ndarray) -> None:
    """Millman fusion (33)-(34) in information form: P^-1 = sum Y_j, x = P sum Y_j x_j, where
    Y_j x_j is the information vector itself for a local still in information form. O is
    (L,) + batch + (n, S n), P (L,) + batch + (n, n)."""
    set_readouts(steps, *msc_fusion(forms, mats))


def msc_fusion(forms: np.ndarray, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`msc_readouts` as arrays over the steps: O (L,) + batch + (n, S n), P (L,) + batch +
    (n, n)."""
    Ys, Ws = local_infos(forms, mats)
    Y = Ys.sum(axis=-3)
    require_finite(Y, "the fused information sum_j P_j^-1", per_step=True)
    P = inv_or_nan(Y)  # each step on its own
    require_fused(forms, P, "Millman's formula")
    return stack_cols(P[..., None, :, :] @ Ws), P


def gmf_readouts(steps: list[StepMap], forms: np.ndarray, joints: list[np.ndarray], n: int) -> None:
    """Eqs. (2)-(7) with the unbiasedness constraint sum_j c_j D_j = I, which is eq. (7) when
    every local is in mean form (D_j = I) and extends it to information form. One call per
    step: lstsq (the shared path's solver) does not batch."""
    for st, form, J in zip(steps, forms, joints, strict=True):
        if not form.any():
            st.O, st.P = gmf_weight_matrix(J, n)  # sign = -I cancels
        else:
            sign = signs(tuple(form.tolist()), n)
            st.O, st.P = gmf_weight_matrix(sign @ J @ sign, n, st.D)


def avg_readouts(
    steps: list[StepMap],
    forms: np.ndarray,
    joints: list[np.ndarray],
    local_O: list[np.ndarray],
    batch: tuple[int, ...],
) -> None:
    """Equal weights on the local means (eq. 2, c_i = I/S) and the covariance they really
    give, eq. (4); undefined (NaN) while a local has no mean yet."""
    S, n = forms.shape[1], local_O[0].shape[-1]
    O = stack_cols(np.stack([bc(o, batch + (S, n, n)) for o in local_O])) / S
    sign = np.stack([signs(tuple(f.tolist()), n) for f in forms])
    Msig = O @ sign.reshape(sign.shape[:1] + (1,) * len(batch) + sign.shape[1:])
    set_readouts(steps, O, sym(Msig @ np.stack(joints) @ mT(Msig)))


def _small_mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B for stacks of small matrices, as n elementwise products over the whole stack:
    matmul calls BLAS once per matrix, which for 10^5 2 x 2 products costs ~30 times more."""
    out = A[..., :, :1] * B[..., :1, :]
    for k in range(1, A.shape[-1]):
        out = out + A[..., :, k : k + 1] * B[..., k : k + 1, :]
    return out


def ci_readouts(
    steps: list[StepMap],
    forms: np.ndarray,
    mats: np.ndarray,
    batch: tuple[int, ...],
    criterion: str,
) -> np.ndarray:
    """Covariance intersection of the local estimates at the first L steps, from the local
    informations Y_j and maps W_j with Y_j x_j = W_j s_j, (L,) + batch + (S, n, n): every step's
    (and run's) omega in one `ci_omegas` call (each problem solved on its own, so the shared
    and the per-run path agree), then P = (sum w_j Y_j)^-1 and the weights
    w_j P W_j written into those steps' maps. In information form a local with too little
    information to have a mean of its own still contributes. `steps` is the whole plan (the
    steps after the L-th repeat one of them). Returns the omegas, batch + (K+1, S)."""
    K1 = len(steps)
    O, P, om = ci_fusion(forms, mats, criterion)
    S = om.shape[-1]
    by_id = {}
    for i in range(len(O)):
        steps[i].O, steps[i].P = O[i], P[i]
        by_id[id(steps[i])] = om[i]
    omega = np.full((K1,) + batch + (S,), np.nan)
    for k, st in enumerate(steps):
        if id(st) in by_id:
            omega[k] = by_id[id(st)]
    return np.moveaxis(omega, 0, -2)


def ci_fusion(
    forms: np.ndarray, mats: np.ndarray, criterion: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`ci_readouts` as arrays over the L steps of `mats`: O (L,) + batch + (n, S n), P (L,) +
    batch + (n, n) and the weights (L,) + batch + (S,)."""
    Ys, Ws = local_infos(forms, mats)
    S, n = Ys.shape[-3], Ys.shape[-1]
    om = ci_omegas(Ys, criterion)  # (L,) + batch + (S,), read in place whatever Ys's layout
    # sum_j w_j Y_j and the weights w_j P W_j written out over j, elementwise over all steps
    # and runs: einsum took ten times longer on the local filters' layout, and matmul calls
    # BLAS once per 2 x 2 matrix.
    Y = om[..., 0, None, None] * Ys[..., 0, :, :]
    for j in range(1, S):
        Y = Y + om[..., j, None, None] * Ys[..., j, :, :]
    P = inv_or_nan(Y)
    require_fused(forms, P, "covariance intersection")
    O = np.empty(P.shape[:-1] + (S * n,))
    for j in range(S):
        np.multiply(
            om[..., j, None, None], _small_mm(P, Ws[..., j, :, :]), out=O[..., j * n : (j + 1) * n]
        )
    return O, P, om
