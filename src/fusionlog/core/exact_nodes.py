"""The exact analysis of a per-run plan on its history nodes.

A per-run plan built on history nodes (`architectures.HistoryNodes`: the runs whose measurement
patterns agree up to step k share one node of step k, and its maps) has the same exact error
statistics for all the runs of a node: the moments of Z_k = [x_k; zeta_k] (`exact`'s recursion)
depend on the true model, which every run shares, and on the maps of the run's nodes at steps
0..k, which are those of the node's ancestors. So the recursion runs once per node, each node
starting from its parent's moments, and each run takes its node's statistics:

    mu_j = A_j mu_parent(j),   C_j = A_j C_parent(j) A_j^T + B_v,j R B_v,j^T + B_w,j GQG B_w,j^T,

then per node the error's mean and MSE matrix through the readout, and the expected NEES and DM
of every node and step in one batch (`quadratic_form.nees_and_dm_many`). With 10 % of the
measurements of three sensors missing there are 56 % as many nodes as run-steps (73 % at 20 %);
the arithmetic is the per-run analysis's, item for item.

The smoother (FBS) is left to the per-run analysis: its backward pass depends on each run's
future pattern, which a node (a shared past) does not fix.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..errors import NumericalError
from .architectures import BlockDiagonal, Plan, StepMap
from .expected import Expected, not_definite
from .linalg import sym
from .model import System
from .moments import congruences, hcat, initial_moments, mv, step_moments
from .quadratic_form import nees_and_dm_many


def _dense(a):
    return a.dense() if isinstance(a, BlockDiagonal) else a


def _per_node(a: np.ndarray, count: int, core: int) -> np.ndarray:
    """a (count, ...) per node, or shared (its last `core` axes only) broadcast to the nodes."""
    return a if a.ndim > core else np.broadcast_to(a, (count,) + a.shape)


def analyse_nodes(plan: Plan, truth: System, where: Callable[[np.ndarray], str]) -> Expected:
    """`exact.analyse` of a per-run plan on history nodes without a smoother: every run's
    exact statistics, (M, K+1, ...), computed once per node (module docstring). `where` names
    the first run and step of a (M, K+1) mask in errors."""
    index = plan.nodes
    n = truth.n
    mu, C, nx = initial_moments(plan, truth)
    Ht = truth.linear_measurement()
    D_prev = plan.D0
    node_stats: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per step: P, bias, mse
    for k, st in enumerate(plan.steps):
        count = int(index[k].max()) + 1
        if k > 0:  # each node continues its parent's moments
            parent = np.empty(count, dtype=np.intp)
            parent[index[k]] = index[k - 1]
            mu = mu[parent] if mu.ndim > 1 else mu
            C = C[parent] if C.ndim > 2 else C
            D_prev = D_prev[parent] if D_prev is not None and D_prev.ndim > 2 else D_prev
        st = StepMap(*(_dense(getattr(st, f)) for f in ("T", "U", "O", "P", "D")))
        mu, C = step_moments(st, k, mu, C, D_prev, truth, nx, Ht)
        if not (np.isfinite(C).all() and np.isfinite(mu).all()):
            raise NumericalError(f"{where(_runs_of(mu, C, k, index))}: the true error covariance "
                                 "overflows")  # fmt: skip
        D_prev = st.D
        L = hcat(np.eye(n) - st.O @ st.D, -st.O) if nx else -st.O
        bias = _per_node(mv(L, mu), count, 1)
        mse = sym(congruences([(L, C)])) + bias[..., :, None] * bias[..., None, :]
        node_stats.append((_per_node(st.P, count, 2), bias, _per_node(mse, count, 2)))
    sizes = [len(s[0]) for s in node_stats]
    P, bias, mse = (np.concatenate([s[i] for s in node_stats]) for i in range(3))
    ok = ~np.isnan(P).any(axis=(-1, -2))
    nees = np.full(len(P), np.nan)
    dm = np.full(len(P), np.nan)
    if ok.any():
        nees[ok], dm[ok], definite = nees_and_dm_many(P[ok], bias[ok], mse[ok])
        if not definite.all():
            failed = np.zeros(len(P), dtype=bool)
            failed[np.flatnonzero(ok)[~definite]] = True
            raise not_definite(where(_to_runs(failed, sizes, index)))
    return Expected(
        _to_runs(mse, sizes, index),
        _to_runs(bias, sizes, index),
        plan.reported_cov,
        _to_runs(nees, sizes, index),
        _to_runs(dm, sizes, index),
    )


def _to_runs(a: np.ndarray, sizes: list[int], index: list[np.ndarray]) -> np.ndarray:
    """Node-steps (sum(sizes), ...) in step order to runs (M, K+1, ...): each run its node's."""
    start = np.cumsum([0] + sizes[:-1])
    flat = np.stack(index, axis=1) + start  # (M, K+1): each run's node-step
    return np.take(a, flat, axis=0)


def _runs_of(mu: np.ndarray, C: np.ndarray, k: int, index: list[np.ndarray]) -> np.ndarray:
    """(M, K+1) mask of the runs at step k whose node's moments are not finite."""
    good = np.isfinite(C).all(axis=(-2, -1)) & np.isfinite(mu).all(axis=-1)
    mask = np.zeros((len(index[0]), len(index)), dtype=bool)
    mask[:, k] = ~good[index[k]] if good.ndim else not good
    return mask
