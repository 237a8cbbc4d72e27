"""Exact covariance analysis: the true error statistics of every architecture, without sampling.

An architecture compiled to a plan (see `architectures`) is a linear map of the data, so the joint
first and second moments of Z_k = [x_k; s_k] (true state and estimator state) propagate exactly:

    x_k = F_t x_{k-1} + w,                 s_k = T_k s_{k-1} + U_k (H_t x_k + v_k),

with the *true* model (F_t, GQG_t, H_t, R_t, initial distribution; F, GQG and R per step where
they vary), which may differ from the model
the filter was built with (model-mismatch studies). The error e_k = x_k - O_k s_k then has mean
mu_k and covariance C_k, and the expected MSE matrix is C_k + mu_k mu_k^T; for track-to-track
architectures this is the joint covariance of all local filters' errors carried along.

For the smoother (FBS) the backward information vector is y_b,k = B_k x_k + eta_k with eta_k
independent of everything up to k; B_k and cov(eta_k) follow a backward recursion.

A per-run plan (runs with their own measurement patterns, e.g. dropouts) is still linear with
deterministic gains given its run's pattern, so each run's error statistics are exact too: the
same recursions run with a leading run axis on every map and moment (matrix products broadcast
over it), for chunks of runs. `ConditionalExpected` averages them over the runs: the expected
values conditional on the drawn patterns, which the Monte Carlo averages estimate.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..errors import NumericalError
from .architectures import BlockDiagonal, Plan, StepMap
from .expected import Expected, not_definite
from .linalg import mT, numerical_errors, sym, wide_diagonal
from .model import System
from .moments import congruences, forward_moments, hcat, mv, rmul
from .quadratic_form import (
    expected_sqrt_quadratic,
    expected_sqrt_quadratic_many,
    nees_and_dm_many,
    whitening,
)

__all__ = [
    "CHUNK_RUNS",
    "ConditionalExpected",
    "Expected",
    "analyse",
    "expected_sqrt_quadratic",
    "expected_sqrt_quadratic_many",
    "not_definite",
    "plan_of_runs",
    "shared_nees_and_dm",
]

#: Runs analysed together in a per-run plan: the moments of a chunk, (runs, d, d) per step,
#: stay a few megabytes whatever the number of runs.
CHUNK_RUNS = 2048


def analyse(plan: Plan, truth: System, *, chunk_runs: int = CHUNK_RUNS) -> Expected:
    """Exact error mean, MSE matrix, expected NEES and expected DM of a plan.

    A shared plan gives (K+1, ...) arrays; a per-run plan each run's statistics given its
    measurement pattern, (M, K+1, ...): on its history nodes when it has them and no smoother
    (`exact_nodes`), else for `chunk_runs` runs at a time.

    Raises NumericalError (naming the architecture, the step and for a per-run plan the run)
    when the true error covariance overflows or the reported covariance is not positive
    definite where the architecture reports one, i.e. when the expected values cannot be
    computed.
    """
    if not plan.per_run:
        return _checked(plan, truth)
    if plan.nodes is not None and plan.smoother is None:  # once per history node
        from .exact_nodes import analyse_nodes

        return _checked(plan, truth, first_run=0, analysis=analyse_nodes)
    nodes = plan.nodes  # maps per measurement history, see plan_of_runs
    M = len(nodes[0]) if nodes is not None else plan.reported_cov.shape[0]
    parts = [
        _checked(plan_of_runs(plan, slice(a, min(a + chunk_runs, M))), truth, first_run=a)
        for a in range(0, M, chunk_runs)
    ]
    if len(parts) == 1:
        return parts[0]
    return Expected(
        *(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(Expected))
    )


def _checked(plan: Plan, truth: System, first_run: int | None = None, analysis=None) -> Expected:
    """`analysis` (default `_analyse`) with its failures named (`first_run`: the first run of a
    per-run chunk)."""

    def where(mask: np.ndarray) -> str:
        """Names the first entry of a (K+1,) or (runs, K+1) mask (or a leading part of it)."""
        at = np.unravel_index(int(np.flatnonzero(mask)[0]), mask.shape)
        if first_run is None:
            return f"step {at[0]}"
        return f"step {at[1]} of run {first_run + at[0]}"

    with numerical_errors(lambda: f"architecture {plan.name}, exact analysis"):
        ex = (analysis or _analyse)(plan, truth, where)
        finite = np.isfinite(ex.mse).all(axis=(-2, -1)) & np.isfinite(ex.nees) & np.isfinite(ex.dm)
        bad = ex.defined & ~finite
        if bad.any():
            raise NumericalError(
                f"{where(bad)}: the expected MSE, NEES or DM is not finite (the reported "
                "covariance is not positive definite to working precision, or the error "
                "covariance overflows)"
            )
    return ex


def plan_of_runs(plan: Plan, runs: slice | int) -> Plan:
    """The plan of some runs of a per-run plan: every per-run map (one with a run axis) cut to
    `runs`; an int gives that run's maps as a shared plan. Maps shared by several steps stay
    shared (the analysis tests steps for identity); block-diagonal ones are made dense. A plan
    whose steps hold maps per measurement history (`nodes`: each run's node at every step)
    gives each run its node's maps."""
    nodes = plan.nodes
    cut: dict[tuple[int, int], np.ndarray] = {}

    def c(a, k: int = -1) -> np.ndarray:
        """Map `a` of step k (-1: a per-run map of the smoother) for the runs."""
        key = (id(a), k if nodes is not None else -1)
        if key not in cut:
            sel = runs if nodes is None or k < 0 else nodes[k][runs]
            if isinstance(a, BlockDiagonal):  # a block-diagonal map kept as its blocks
                b = a.blocks[sel] if a.ndim == 3 else a.blocks
                cut[key] = dataclasses.replace(a, blocks=b).dense()
            else:
                cut[key] = a[sel] if a.ndim == 3 else a
        return cut[key]

    steps: dict[tuple[int, int], StepMap] = {}
    for k, st in enumerate(plan.steps):
        key = (id(st), k if nodes is not None else -1)
        if key not in steps:
            D = None if st.D is None else c(st.D, k)
            maps = {"T": c(st.T, k), "U": c(st.U, k), "O": c(st.O, k), "P": c(st.P, k)}
            steps[key] = dataclasses.replace(st, D=D, **maps)
    sm = plan.smoother
    if sm is not None:
        sm = dataclasses.replace(
            sm, **{f: [c(a) for a in getattr(sm, f)] for f in ("L", "V", "A", "B", "P")}
        )
    return dataclasses.replace(
        plan,
        steps=[steps[id(st), k if nodes is not None else -1] for k, st in enumerate(plan.steps)],
        smoother=sm,
        per_run=plan.per_run and not isinstance(runs, int),
        omega=None,  # not used by the analysis
        dense=None,
        **({"nodes": None} if "nodes" in {f.name for f in dataclasses.fields(plan)} else {}),
    )


#: Distinct statistics of a shared plan above which DM takes the fitted grid: a scenario's
#: filters settle to a few (the fixed 1601-node grid costs nothing there), a recorded log's
#: instants are all distinct (replay_robot, 7 architectures: 1.8 s fixed, ~0.1 s fitted).
FIXED_GRID_ITEMS = 256


def shared_nees_and_dm(
    P: np.ndarray, bias: np.ndarray, mse: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expected NEES tr(P^-1 E[e e^T]) and DM (eq. 46) of the steps (N, ...) of a shared plan
    whose reported P are all finite, and which P are positive definite to working precision
    (where one is not, the NEES and DM are not meaningful: the caller names the step)."""
    W = whitening(P)
    definite = np.isfinite(W).all(axis=(-2, -1))
    if not definite.all():
        return np.full(len(P), np.nan), np.full(len(P), np.nan), definite
    # For badly scaled P (see whitening) P^-1 = W^T W; otherwise LU's inverse.
    Pinv = mT(W) @ W if wide_diagonal(P) else np.linalg.inv(P)
    nees = np.einsum("kij,kji->k", Pinv, mse)
    cov = mse - np.einsum("ki,kj->kij", bias, bias)
    # Steady-state steps repeat the same statistics: integrate each distinct one once.
    key = np.concatenate([P.reshape(len(P), -1), bias, cov.reshape(len(cov), -1)], 1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    # DM, eq. (46), of each: the fixed grid for a few, the fitted one beyond FIXED_GRID_ITEMS.
    Pd, bd, cd = P[first], bias[first], cov[first]
    if len(first) <= FIXED_GRID_ITEMS:
        dm = expected_sqrt_quadratic(Pd, bd, cd)[inverse.ravel()]
    else:
        dm = expected_sqrt_quadratic_many(Pd, bd, cd, W[first])[inverse.ravel()]
    return nees, dm, definite


def _analyse(plan: Plan, truth: System, where) -> Expected:
    n = truth.n
    mus, Cs, nx, settled = forward_moments(plan, truth)
    K1 = len(plan.steps)
    P = plan.reported_cov
    batch = P.shape[:-3]  # () for a shared plan, (runs,) for a per-run one

    def readout(A: np.ndarray, D: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """Row block L with e = L Z - (noise terms): e = (I - A D - extra) x - A zeta."""
        if nx:
            return hcat(np.eye(n) - A @ D - extra, -A)
        return -A

    def outer(b: np.ndarray) -> np.ndarray:
        return b[..., :, None] * b[..., None, :]

    bias = np.empty(batch + (K1, n))
    mse = np.empty(batch + (K1, n, n))
    if plan.smoother is None:
        for k, st in enumerate(plan.steps[: settled + 1]):
            Lk = readout(st.O, st.D, 0.0)
            bias[..., k, :] = mv(Lk, mus[k])
            mse[..., k, :, :] = sym(congruences([(Lk, Cs[k])])) + outer(bias[..., k, :])
        if settled < K1:  # steady state: the same map of the same moments at every later step
            bias[..., settled + 1 :, :] = bias[..., settled, None, :]
            mse[..., settled + 1 :, :, :] = mse[..., settled, None, :, :]
    else:
        sm = plan.smoother
        Ht = truth.linear_measurement()
        Bk = np.zeros((n, n))
        Ceta = np.zeros((n, n))
        steady = False  # backward statistics stopped changing under a repeated map
        # repeated[k]: step k's backward map is step k + 1's; same[k]: and so is everything
        # step k's statistics are made of, so in the steady state they are step k + 1's.
        repeated = [sm.L[k] is sm.L[k + 1] and sm.V[k + 1] is sm.V[k + 2] for k in range(K1 - 2)]
        repeated += [False, False]
        same = [
            rep and a is a1 and b is b1 and s is s1 and m is m1 and c is c1
            for rep, a, a1, b, b1, s, s1, m, m1, c, c1 in zip(
                repeated,
                sm.A, sm.A[1:], sm.B, sm.B[1:], plan.steps, plan.steps[1:],
                mus, mus[1:], Cs, Cs[1:], strict=False,  # the shifted lists are one shorter
            )
        ]  # fmt: skip
        same += [False]
        # run_start[k]: first step of the stretch of `same` steps that ends at k
        idx = np.arange(K1)
        run_start = np.maximum.accumulate(np.where(same, -1, idx)) + 1
        k = K1 - 1
        while k >= 0:
            steady = steady and repeated[k]
            if steady and same[k]:  # the steady stretch repeats step k + 1's statistics
                j = int(run_start[k])
                bias[..., j : k + 1, :] = bias[..., k + 1, None, :]
                mse[..., j : k + 1, :, :] = mse[..., k + 1, None, :, :]
                k = j - 1
                continue
            if k < K1 - 1 and not steady:
                V = sm.V[k + 1]
                Bplus = Bk + rmul(V, Ht)
                Cplus = Ceta + congruences([(V, truth.R_at(k + 1))])
                # L is about the inverse of the information in B+ and C+: multiplying it in
                # first keeps B+ Q B+' (the square of an information) from overflowing.
                LB = sm.L[k] @ Bplus
                B_new = rmul(LB, truth.F_at(k + 1))
                C_new = sym(congruences([(LB, truth.GQG_at(k + 1)), (sm.L[k], Cplus)]))
                steady = repeated[k] and all(
                    np.abs(new - old).max() <= 1e-15 * max(np.abs(new).max(), 1e-300)
                    for new, old in ((B_new, Bk), (C_new, Ceta))
                )
                Bk, Ceta = B_new, C_new
            # e = x - A s_f - B (B_k x + eta) = (I - A D - B B_k) x - A zeta - B eta; with the
            # true model I - A D - B B_k vanishes and B_k x is dropped with x (see coupling).
            Lk = readout(sm.A[k], plan.steps[k].D, sm.B[k] @ Bk)
            bias[..., k, :] = mv(Lk, mus[k])
            mse[..., k, :, :] = sym(congruences([(Lk, Cs[k]), (sm.B[k], Ceta)])) + outer(
                bias[..., k, :]
            )
            k -= 1
    nees = np.full(batch + (K1,), np.nan)
    dm = np.full(batch + (K1,), np.nan)
    # A filter's statistics and reported covariance repeat after `settled`: compute them once.
    m = settled + 1 if plan.smoother is None and settled < K1 else K1
    ok = ~np.isnan(P[..., :m, :, :]).any(axis=(-1, -2))
    if ok.any():
        Pk, bk, mk = P[..., :m, :, :][ok], bias[..., :m, :][ok], mse[..., :m, :, :][ok]
        if batch:  # every run and step: closed forms and fitted grids (nees_and_dm_many)
            nees_k, dm_k, definite = nees_and_dm_many(Pk, bk, mk)
        else:
            nees_k, dm_k, definite = shared_nees_and_dm(Pk, bk, mk)
        if not definite.all():
            failed = np.zeros_like(ok)
            failed[ok] = ~definite
            raise not_definite(where(failed))
        nees[..., :m][ok] = nees_k
        dm[..., :m][ok] = dm_k
    nees[..., m:] = nees[..., m - 1, None]
    dm[..., m:] = dm[..., m - 1, None]
    return Expected(mse, bias, P, nees, dm)


@dataclass
class ConditionalExpected:
    """Run averages of per-run exact statistics: the expected values conditional on the drawn
    measurement patterns, accumulated over blocks of runs (`add` each block's `analyse`).

    Per step k, over the runs whose estimate is defined at k (the architecture reports a
    covariance there: the entries the Monte Carlo metrics keep, `metrics` eqs. 44-46),

        mse_k = sum_r diag E_r[e_k e_k^T] / M_k,   nees_k = sum_r E_r[NEES_k] / M_k,
        dm_k = sum_r E_r[DM_k] / M_k,

    which is what the Monte Carlo per-step averages estimate, given the patterns; NaN where no
    run is defined.
    """

    n_steps: int  # K + 1
    n_states: int  # n
    runs: int = 0
    count: np.ndarray = field(init=False)  # (K+1,) runs with a defined estimate
    mse_sum: np.ndarray = field(init=False)  # (K+1, n)
    nees_sum: np.ndarray = field(init=False)  # (K+1,)
    dm_sum: np.ndarray = field(init=False)  # (K+1,)
    #: (K+1,) the bound check's ratio (`core.bound`), the worst over the runs (NaN: none)
    bound_max: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.count = np.zeros(self.n_steps, dtype=np.int64)
        self.mse_sum = np.zeros((self.n_steps, self.n_states))
        self.nees_sum = np.zeros(self.n_steps)
        self.dm_sum = np.zeros(self.n_steps)
        self.bound_max = np.full(self.n_steps, np.nan)

    def add(self, ex: Expected, runs: int = 1) -> None:
        """Add the per-run statistics (M, K+1, ...) of a block of runs, or those of a shared
        plan (K+1, ...) as `runs` runs with that pattern."""
        mse, nees, dm, ok, bound = ex.mse_per_state, ex.nees, ex.dm, ex.defined, ex.bound
        if nees.ndim == 1:
            mse, nees, dm, ok, bound = mse[None], nees[None], dm[None], ok[None], bound[None]
        else:
            runs = 1
        if nees.shape[1:] != (self.n_steps,) or mse.shape[2:] != (self.n_states,):
            raise ValueError(
                f"statistics of {nees.shape[1:]} steps and {mse.shape[2:]} states, "
                f"expected ({self.n_steps},) and ({self.n_states},)"
            )
        self.runs += runs * nees.shape[0]
        self.count += runs * ok.sum(axis=0)
        self.mse_sum += runs * np.where(ok[..., None], mse, 0.0).sum(axis=0)
        self.nees_sum += runs * np.where(ok, nees, 0.0).sum(axis=0)
        self.dm_sum += runs * np.where(ok, dm, 0.0).sum(axis=0)
        # fmax: NaN (no estimate) loses to any number, and NaN only where every run has none
        self.bound_max = np.fmax(self.bound_max, np.fmax.reduce(np.where(ok, bound, np.nan)))

    def merge(self, other: ConditionalExpected) -> ConditionalExpected:
        """Add another accumulator's sums (same steps and states) into this one; returns self."""
        if (other.n_steps, other.n_states) != (self.n_steps, self.n_states):
            raise ValueError("cannot merge accumulators of different shapes")
        self.runs += other.runs
        for name in ("count", "mse_sum", "nees_sum", "dm_sum"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.bound_max = np.fmax(self.bound_max, other.bound_max)
        return self

    def _mean(self, total: np.ndarray) -> np.ndarray:
        c = self.count.reshape(self.count.shape + (1,) * (total.ndim - 1))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(c > 0, total / np.maximum(c, 1), np.nan)

    @property
    def mse_per_state(self) -> np.ndarray:
        """(K+1, n) run-averaged expected MSE of each state component (eq. 44)."""
        return self._mean(self.mse_sum)

    @property
    def nees(self) -> np.ndarray:
        """(K+1,) run-averaged expected NEES."""
        return self._mean(self.nees_sum)

    @property
    def dm(self) -> np.ndarray:
        """(K+1,) run-averaged expected DM (eq. 46)."""
        return self._mean(self.dm_sum)

    @property
    def bound(self) -> np.ndarray:
        """(K+1,) the bound check's ratio, the worst over the runs given their patterns."""
        return self.bound_max
