"""The plan executor: a compiled plan applied to the measurements of M runs.

The step recursion s_k = T_k s_{k-1} + U_k z_k, x_hat_k = O_k s_k (plus FBS's backward pass
y_b[k] = L_k (y_b[k+1] + V_{k+1} z_{k+1}), x_hat_k = A_k s_k + B_k y_b[k], eqs. 25-28) is linear
in z, so it can be applied three ways that compute the same map:

* a shared plan over a short horizon as one dense matrix of the whole history (one GEMM);
* the plain recursion, one step at a time for all runs (one GEMM per step);
* with few runs and a long steady state, the repeated map in blocks of STEADY_BLOCK steps.

A per-run plan (maps with a leading run axis) runs the recursion with the runs as the last,
contiguous axis of the state (`linalg.lanes`): one einsum per map and step, whose
sum-of-products loops run over the runs, instead of a stacked product of 10^4 tiny matrices.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ...errors import NumericalError
from ..linalg import apply, bc, lanes, mT, mv
from .plan import BlockDiagonal, DenseMap, Estimate, Plan, SmootherMaps, take_map

#: Horizons up to this many instants apply a shared plan as one dense linear map.
DENSE_MAX_STEPS = 128

#: A steady tail of a plan run on at most FEW_RUNS runs goes through in blocks of STEADY_BLOCK
#: steps: with few runs the per-step numpy calls, not the arithmetic, are the cost.
FEW_RUNS = 16
STEADY_BLOCK = 32

Route = Literal["auto", "steps"]


def run_plan(plan: Plan, z: np.ndarray, *, route: Route = "auto") -> Estimate:
    """Apply a plan to measurements z (M, K+1, m); NaN entries must be absent in the plan's mask.

    A shared plan over a short horizon is one affine map of the whole measurement history,
    mean = W vec(z) + c, applied to all runs as a single GEMM on the contiguous (M, (K+1) m)
    view of z. W and c are the plan's responses to unit measurements and to no data, obtained by
    running the step recursion on a basis, so both routes compute the same linear map.
    Longer horizons and per-run plans run the step recursion itself. `route="steps"` runs the
    plain step recursion whatever the plan (the reference the faster routes are checked with).
    """
    M, K1, m = z.shape
    cov = plan.reported_cov
    if route == "steps" or plan.per_run or K1 > DENSE_MAX_STEPS:
        with np.errstate(over="ignore", invalid="ignore"):
            if plan.per_run:
                mean = _recursion_per_run(plan, z)
            else:
                mean = _recursion(plan, np.where(np.isnan(z), 0.0, z), blocks=route != "steps")
        _require_defined(plan, mean, cov)
        return Estimate(mean, cov)
    if plan.dense is None:
        # The linear part from unit measurements with a zero initial state, the constant from
        # the initial state with no data: no subtraction, so a large prior mean (UTM metres)
        # cannot cancel the small gains away.
        basis = np.eye(K1 * m).reshape(K1 * m, K1, m)
        with np.errstate(over="ignore", invalid="ignore"):
            W = _recursion(plan, basis, np.zeros_like(plan.s0))
            c = _recursion(plan, np.zeros((1, K1, m)))
        plan.dense = DenseMap(W.reshape(K1 * m, -1), c.reshape(-1))
    W, c = plan.dense.W, plan.dense.c
    nan_zeroed = False
    if not plan.complete and np.isnan(z).any():  # absent in the plan's mask: zero weight there
        z, nan_zeroed = np.where(np.isnan(z), 0.0, z), True
    mean = _dense(z, W, c)
    # One pass over the means finds an overflow, and NaN measurements that a plan without
    # absent components was given after all (the old contract: they count as absent, i.e. as
    # 0 -- looked for only now, which saves complete plans a pass over z).
    if not np.isfinite(mean).all():
        if not nan_zeroed and np.isnan(z).any():
            mean = _dense(np.where(np.isnan(z), 0.0, z), W, c)
        if not np.isfinite(mean).all():  # the dense map mixes all steps: the recursion says
            with np.errstate(over="ignore", invalid="ignore"):  # where it overflows
                mean = _recursion(plan, np.where(np.isnan(z), 0.0, z), blocks=False)
        _require_defined(plan, mean, cov)
    return Estimate(mean, cov)


def _dense(z: np.ndarray, W: np.ndarray, c: np.ndarray) -> np.ndarray:
    """vec(z) W + c for each run, as one GEMM on the contiguous (M, (K+1) m) view of z."""
    M, K1, m = z.shape
    with np.errstate(over="ignore", invalid="ignore"):
        mean = np.ascontiguousarray(z).reshape(M, K1 * m) @ W
        mean += c
    return mean.reshape(M, K1, -1)


def _require_defined(plan: Plan, mean: np.ndarray, cov: np.ndarray) -> None:
    """Refuse estimates that are not finite where the plan reports a covariance (mean
    (M, K+1, n); cov (K+1, n, n) or (M, K+1, n, n)): the gains of a badly conditioned model,
    or measurements of ~1e300, overflowed. Undefined estimates (NaN covariance) may be NaN.
    The usual all-finite case costs one pass over the means."""
    if np.isfinite(mean).all():
        return
    defined = np.isfinite(cov).all(axis=(-2, -1))  # (K+1,) or (M, K+1)
    bad = defined & ~np.isfinite(mean).all(axis=-1)
    if bad.any():
        k = int(np.flatnonzero(bad.any(axis=0))[0])
        raise NumericalError(
            f"architecture {plan.name}, step {k}: the estimate overflows (gains or "
            "measurements beyond the float range, about 1.8e308)"
        )


def _recursion(
    plan: Plan,
    z: np.ndarray,
    s0: np.ndarray | None = None,
    blocks: bool = True,
    last: list | None = None,
) -> np.ndarray:
    """The step recursion s_k = T s_{k-1} + U z_k, x_k = O s_k (and FBS's backward pass); with
    `blocks`, a long steady tail on few runs in blocks of steps. `last` (a list) receives the
    final state s_K (a log in blocks of time carries it into the next block)."""
    M, K1, _ = z.shape
    s0 = plan.s0 if s0 is None else s0
    s = bc(s0, (M, s0.shape[0]))
    n = plan.steps[0].O.shape[-2]
    out = np.empty((M, K1, n))
    states = [] if plan.smoother is not None else None
    # With few runs the per-step numpy calls, not the arithmetic, are the cost: a long steady
    # tail (a 10^5-step log) is run in blocks instead, a few GEMMs for all of it.
    few_runs = blocks and not plan.per_run and M <= FEW_RUNS
    n_blocks = 0
    if few_runs:
        n_blocks = (K1 - plan.steady_from) // STEADY_BLOCK
        n_blocks = n_blocks if n_blocks >= 2 else 0
    head = K1 - n_blocks * STEADY_BLOCK
    for k in range(head):
        st = plan.steps[k]
        s = apply(st.T, s) + apply(st.U, z[:, k])
        if states is not None:
            states.append(s)
        else:
            out[:, k] = apply(st.O, s)
    if n_blocks:
        st = plan.steps[-1]
        tail = _steady_states(st.T, st.U, s, z[:, head:])  # (M, n_blocks * STEADY_BLOCK, d)
        if states is not None:
            states.extend(tail[:, j] for j in range(tail.shape[1]))
        else:
            out[:, head:] = tail @ st.O.T
        s = tail[:, -1]
    if last is not None:
        last.append(s)
    if plan.smoother is not None:
        _smooth(plan.smoother, states, z, out, few_runs)
    return out


def _recursion_per_run(plan: Plan, z: np.ndarray) -> np.ndarray:
    """`_recursion` for a per-run plan (NaN in z counts as 0), on lanes: the state is (d, M),
    a step's measurements (m, M). Nothing of the size of z or of the means is allocated
    besides the means themselves: in this kind of VM the page faults of fresh multi-megabyte
    arrays cost more than the arithmetic in them."""
    M, K1, m = z.shape
    s = np.empty((plan.s0.shape[0], M))
    s[...] = plan.s0[:, None]
    n = plan.steps[0].O.shape[-2]
    out = np.empty((M, K1, n))
    states = []
    zk = np.empty((K1 if plan.smoother is not None else 1, m, M))

    def measured(k: int) -> np.ndarray:
        """z_k as lanes (m, M), NaN as 0 (kept for the smoother's backward pass)."""
        zz = zk[k if len(zk) > 1 else 0]
        zz[...] = z[:, k].T
        np.copyto(zz, 0.0, where=np.isnan(zz))
        return zz

    for k in range(K1):
        st = plan.steps[k]
        idx = None if plan.nodes is None else plan.nodes[k]  # maps per history node
        T, U = take_map(st.T, idx), take_map(st.U, idx)
        s = _transition(T, s) + mv(_lanes(U), measured(k))
        if plan.smoother is not None:
            states.append(s)
        else:
            out[:, k] = mv(_lanes(take_map(st.O, idx)), s).T
    sm = plan.smoother
    if sm is not None:
        yb = np.zeros((n, M))
        for k in range(K1 - 1, -1, -1):
            if k < K1 - 1:
                yb = mv(_lanes(sm.L[k]), yb + mv(_lanes(sm.V[k + 1]), zk[k + 1]))
            out[:, k] = (mv(_lanes(sm.A[k]), states[k]) + mv(_lanes(sm.B[k]), yb)).T
    return out


def _transition(T: np.ndarray | BlockDiagonal, s: np.ndarray) -> np.ndarray:
    """T s on lanes (s: (d, M)); a block-diagonal T block by block."""
    if not isinstance(T, BlockDiagonal):
        return mv(_lanes(T), s)
    B = T.blocks  # (M, S, a, b): memory (S, a, b, M), see linalg.buffer
    Bl = np.moveaxis(lanes(B), -1, 0)  # (S, a, b, M)
    S, _, b = Bl.shape[:3]
    out = np.einsum("iab...,ib...->ia...", Bl, s.reshape((S, b) + s.shape[1:]))
    return out.reshape((-1,) + s.shape[1:])


def _lanes(A: np.ndarray) -> np.ndarray:
    """A per-run map as lanes (d, e, M); a map shared by the runs as it is (d, e)."""
    return A if A.ndim == 2 else lanes(A)


def _smooth(
    sm: SmootherMaps, states: list[np.ndarray], z: np.ndarray, out: np.ndarray, few_runs: bool
) -> None:
    """FBS's backward pass into `out`; its steady middle, with few runs, in blocks as well."""
    M, K1, _ = z.shape
    yb = np.zeros((M, out.shape[-1]))
    a, b = _steady_segment(sm, K1) if few_runs else (0, -1)
    k = K1 - 1
    while k >= 0:
        if k == b:
            # y_b[k] = L y_b[k+1] + (L V) z[k+1] for k = b..a: the forward recursion on the
            # reversed inputs z[b+1], ..., z[a+1]
            Lm = sm.L[b]
            Y = _steady_states(Lm, Lm @ sm.V[b + 1], yb, z[:, b + 1 : a : -1])[:, ::-1]
            S = np.stack(states[a : b + 1], axis=1)
            out[:, a : b + 1] = S @ mT(sm.A[b]) + Y @ mT(sm.B[b])
            yb, k = Y[:, 0], a - 1
            continue
        if k < K1 - 1:
            yb = apply(sm.L[k], yb + apply(sm.V[k + 1], z[:, k + 1]))
        out[:, k] = apply(sm.A[k], states[k]) + apply(sm.B[k], yb)
        k -= 1


def _steady_segment(sm: SmootherMaps, K1: int) -> tuple[int, int]:
    """(a, b): the longest run of steps k <= K-1 with the same backward and fusion maps, cut to
    a multiple of STEADY_BLOCK steps (at least two blocks); (0, -1) if there is none."""
    best, start = (0, -1), 0
    for k in range(1, K1 - 1):
        if not (
            sm.L[k] is sm.L[k - 1]
            and sm.V[k + 1] is sm.V[k]
            and sm.A[k] is sm.A[k - 1]
            and sm.B[k] is sm.B[k - 1]
        ):
            start = k
        if k - start > best[1] - best[0]:
            best = (start, k)
    a, b = best
    N = (b - a + 1) // STEADY_BLOCK * STEADY_BLOCK
    return (b - N + 1, b) if N >= 2 * STEADY_BLOCK else (0, -1)


def _steady_states(T: np.ndarray, U: np.ndarray, s: np.ndarray, z: np.ndarray) -> np.ndarray:
    """States s_1..s_N of the time-invariant recursion s_j = T s_{j-1} + U z_j from s (M, d),
    z (M, N, m), N a multiple of STEADY_BLOCK = L.

    Within a block, state j (from 0) is T^(j+1) s_init + sum_(i <= j) T^(j-i) U z_i: one GEMM
    gives every block's response to its own inputs, one more adds the response to its initial
    state; only the B block-initial states go through a sequential loop.
    """
    M, N, m = z.shape
    d, L = T.shape[0], STEADY_BLOCK
    B = N // L
    Tp = np.empty((L, d, d))  # Tp[j] = T^(j+1)
    Tp[0] = T
    for j in range(1, L):
        Tp[j] = T @ Tp[j - 1]
    TU = np.concatenate([U[None], Tp[:-1] @ U])  # TU[q] = T^q U
    G = np.zeros((L, m, L, d))  # (input i, its component) -> (state j, its component)
    for i in range(L):
        G[i, :, i:, :] = TU[: L - i].transpose(2, 0, 1)
    G = G.reshape(L * m, L * d)
    Phi = Tp.transpose(2, 0, 1).reshape(d, L * d)  # initial state -> the block's states
    S = (np.ascontiguousarray(z).reshape(M, B, L * m) @ G).reshape(M, B, L, d)
    starts = np.empty((M, B, d))
    TL = Tp[-1].T
    for b in range(B):
        starts[:, b] = s
        s = S[:, b, -1] + s @ TL
    S += (starts @ Phi).reshape(M, B, L, d)
    return S.reshape(M, N, d)
