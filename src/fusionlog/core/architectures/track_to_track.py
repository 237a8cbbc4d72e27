"""Track-to-track fusion: local KFs without feedback, one per sensor, and a fusion rule applied to
their estimates at every step (the readout x_hat = O s, P of the plan):

* MSC      Millman's formula assuming independent local errors, eqs. (32)-(34);
* MSC-GMF  the generalised Millman formula with the exact cross-covariances, eqs. (6)-(7), (35);
* CI       covariance intersection ("safe fusion", Gustafsson-Hendeby);
* AVG      the plain average of the local means with the covariance it really has, eq. (4).

The local filters' joint error covariance follows eq. (35), extended by K_i R_ij K_j^T for
correlated sensor noise and by information-form errors for filters started without a prior.
The local filters run as one stack (`KalmanStack` on `Rows.per_sensor`); the fusion rules, which
do not feed back, are evaluated for all steps together after the recursion (`readouts`). A
per-run plan takes the same rules written with the batch kernels (`mm`, `solve`, ...) below:
numpy's stacked products in `readouts` would cost a microsecond per run and step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...errors import NumericalError
from ..fusion import gmf_weight_matrix
from ..linalg import (
    all_finite,
    apply_shared,
    bc,
    buffer,
    inv_or_nan,
    lanes,
    lanes_copy,
    lanes_empty,
    mm,
    mT,
    require_finite,
    solve_spd_or_flag,
    spd_inv,
    stack_cols,
    stack_diag,
    stack_matrices,
    stack_rows,
    sym,
    take_runs,
    unlanes,
)
from .definition import Architecture
from .filters import KalmanStack, Rows, Steady, fill
from .plan import BlockDiagonal, BuildRequest, Plan, StepMap
from .readouts import (
    avg_readouts,
    ci_readouts,
    gmf_readouts,
    local_infos,
    msc_readouts,
    require_fused,
    set_readouts,
    signs,
)


@dataclass
class LocalHistory:
    """The local filters' recursion: the plan's steps (readouts O, P still to be set) and,
    after each computed step (L of them; the steps after repeat the last), the locals' forms
    (L, S) (True: information form), their matrices (covariance, or information in information
    form), their joint error covariance J of eq. (35) (when asked for), and their readouts
    x_j = O_j s_j. With a per-step readout (`local_filters`), the matrices, J and the local
    readouts are handed to it and not kept (empty lists)."""

    steps: list[StepMap]
    forms: np.ndarray
    matrices: list[np.ndarray]
    joints: list[np.ndarray]
    readouts: list[np.ndarray]
    s0: np.ndarray
    D0: np.ndarray

    @property
    def mats(self) -> np.ndarray:
        """The locals' matrices, (L,) + batch + (S, n, n)."""
        return stack_matrices(self.matrices)

    @property
    def computed(self) -> list[StepMap]:
        """The steps computed one by one (the rest repeat the last of them)."""
        return self.steps[: len(self.forms)]


#: A fusion rule applied at every step as the local filters advance (the per-run path, where
#: keeping every step's matrices for a rule over all steps would cost more memory than the
#: plan itself): (step map to complete with O and P, the locals' forms (S,), their matrices,
#: J of eq. (35) or None, their readouts O_j).
StepReadout = Callable[[StepMap, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray], None]


def local_filters(
    request: BuildRequest, joint: bool, readout: StepReadout | None = None
) -> LocalHistory:
    """Run the stack of local KFs over the horizon; with `joint`, carry eq. (35) along; with a
    `readout`, apply it at every step instead of keeping what it needs."""
    system, present, batch = request.system, request.present, request.batch
    n = system.n
    S = len(system.sensors)
    GQG = system.GQG
    locs = KalmanStack(system, Rows.per_sensor(system), batch)
    everything = Rows.all_of(system)  # masked per step for eq. (35)
    if system.prior is not None:
        J = bc(np.kron(np.ones((S, S)), system.prior.cov), batch + (S * n, S * n))
    else:
        J = bc(np.zeros((S * n, S * n)), batch + (S * n, S * n))
    # Per run, J's products go block by block (`_diag_congruence`): Psi and Phi are
    # block-diagonal, and a dense (S n)^3 product per run would cost S^2 times more.
    blocks = bool(batch)
    J = lanes_copy(J) if blocks else J.copy()
    # When every local is in covariance form they all predict with F and the full process
    # noise: Phi and Gam of eq. (35), and the noise term, are then the same at every step.
    Phi_cov = stack_diag(bc(system.F, (S, n, n)))
    Gam_cov = D_cov = stack_rows(locs.I)  # and D_j = I
    GQG_cov = mm(mm(Gam_cov, GQG), mT(Gam_cov))
    steps: list[StepMap] = []
    forms, mats, joints, readouts = [], [], [], []
    steady = Steady(present, system)
    K1 = request.horizon
    for k in range(K1):
        parent = request.begin(k)  # on history nodes: each node continues its parent's
        first = k == 0
        st = locs.step(request.mask(k), k, parent)
        stack = locs.mat.shape  # batch + (S, n, n)
        if joint and parent is not None:
            J = take_runs(J, parent)
        if joint:
            if not first and not system.time_invariant:
                GQG = system.GQG_at(k)
                if st.Phi is locs.F:
                    Phi_cov = stack_diag(bc(locs.F, (S, n, n)))
                    GQG_cov = mm(mm(Gam_cov, GQG), mT(Gam_cov))
            if not first and st.Phi is locs.F and blocks:
                J = _diag_congruence(locs.F, J) + GQG_cov
            elif not first and st.Phi is locs.F:  # every local predicted in covariance form
                J = mm(mm(Phi_cov, J), mT(Phi_cov)) + GQG_cov
            elif not first:
                Phi = stack_diag(bc(st.Phi, stack))
                Gam = stack_rows(bc(st.Gam, stack))
                J = mm(mm(Phi, J), mT(Phi)) + mm(mm(Gam, GQG), mT(Gam))
            _, Rk = everything.masked(request.mask(k), k)
            if blocks:
                J = sym(_diag_congruence(st.Psi, J) + _rows_congruence(st.Lam, Rk))
            else:
                Psi = stack_diag(bc(st.Psi, stack))
                Lam = stack_rows(st.Lam)
                J = sym(mm(mm(Psi, J), mT(Psi)) + mm(mm(Lam, Rk), mT(Lam)))
        T = BlockDiagonal(bc(st.T, stack)) if blocks else stack_diag(bc(st.T, stack))
        # A local's state s_j is D_j x + sigma_j with sigma_j = -g_j (mean form: s = x_hat,
        # g = x - x_hat) or +g_j (information form: s = y, g = y - Y x); J is cov(g).
        D = D_cov if st.D is locs.I else stack_rows(bc(st.D, stack))  # D_j = I: mean form
        step = StepMap(T, stack_rows(st.U), None, None, D)  # O, P: set by a readout
        steps.append(step)
        forms.append(locs.info)
        if readout is not None:
            if joint and not all_finite(J):
                require_finite(J, "the local filters' joint error covariance")
            readout(step, locs.info, locs.mat, J if joint else None, st.O)
        else:
            mats.append(locs.mat)
            joints.append(J)
            readouts.append(st.O)
        if not locs.any_info and steady.reached(J if joint else locs.mat):
            fill(steps, K1)
            break
    request.step = None  # the readouts process every step at once
    return LocalHistory(steps, np.stack(forms), mats, joints, readouts, locs.s0, locs.D0)


def _diag_congruence(A: np.ndarray, J: np.ndarray) -> np.ndarray:
    """D J D^T for D = blockdiag(A_1, ..., A_S), per run and block by block: A batch +
    (S, n, n), or one (n, n) for every block; J batch + (S n, S n). Lanes in and out."""
    n = A.shape[-1]
    S = J.shape[-1] // n
    Jb = lanes(J).reshape((S, n, S, n) + J.shape[:-2])
    out = buffer((S, n, S, n), J.shape[:-2])
    if A.ndim == 2:  # F: A J_ij A^T for every block, on whole slabs of J
        AJ = buffer((S, n, S, n), J.shape[:-2])
        apply_shared(A, Jb, 1, AJ)
        apply_shared(A, AJ, 3, out)
    else:
        Ai = np.moveaxis(lanes(A), -1, 0)  # (S, n, n) + batch
        AJ = np.einsum("iab...,ibjc...->iajc...", Ai, Jb)
        np.einsum("iajc...,jdc...->iajd...", AJ, Ai, out=out)
    return unlanes(out.reshape((S * n, S * n) + J.shape[:-2]))


def _rows_congruence(L: np.ndarray, R: np.ndarray) -> np.ndarray:
    """L R L^T for the stacked rows L = [L_1; ...; L_S] of L (batch + (S, n, m)), per run;
    R batch + (m, m) or shared. Lanes out."""
    S, n = L.shape[-3:-1]
    Li = np.moveaxis(lanes(L), -1, 0)  # (S, n, m) + batch
    if R.ndim == 2:
        LR = np.einsum("iau...,uv->iav...", Li, R)
    else:
        LR = np.einsum("iau...,uv...->iav...", Li, lanes(R))
    out = buffer((S, n, S, n), L.shape[:-3])
    np.einsum("iav...,jdv...->iajd...", LR, Li, out=out)
    return unlanes(out.reshape((S * n, S * n) + L.shape[:-3]))


def _plan(request: BuildRequest, hist: LocalHistory, omega: np.ndarray | None = None) -> Plan:
    batch = request.batch
    plan = Plan(request.name, hist.s0, hist.steps, per_run=bool(batch), D0=hist.D0, omega=omega)
    plan.nodes = request.node_index
    return plan


def build_msc(request: BuildRequest) -> Plan:
    """Millman's formula on the local estimates, eqs. (32)-(34)."""
    if request.batch:
        return _plan(request, local_filters(request, joint=False, readout=_msc_step))
    hist = local_filters(request, joint=False)
    msc_readouts(hist.computed, hist.forms, hist.mats)
    return _plan(request, hist)


def _checked_joints(hist: LocalHistory) -> None:
    """J of eq. (35) is only multiplied in the recursion, so an overflow there (once non-finite,
    it stays so) is looked for once, before a fusion rule solves with it."""
    require_finite(
        np.stack(hist.joints), "the local filters' joint error covariance", per_step=True
    )


def build_msc_gmf(request: BuildRequest) -> Plan:
    """The generalised Millman formula with the exact cross-covariances, eqs. (6)-(7), (35)."""
    if request.batch:
        step = GmfStep(request.system.n, request.present if request.nodes is None else None)
        return _plan(request, local_filters(request, joint=True, readout=step))
    hist = local_filters(request, joint=True)
    _checked_joints(hist)
    gmf_readouts(hist.computed, hist.forms, hist.joints, request.system.n)
    return _plan(request, hist)


def build_avg(request: BuildRequest) -> Plan:
    """The plain average of the local means and its true covariance, eq. (4)."""
    if request.batch:
        return _plan(request, local_filters(request, joint=True, readout=_avg_step))
    hist = local_filters(request, joint=True)
    _checked_joints(hist)
    avg_readouts(hist.computed, hist.forms, hist.joints, hist.readouts, request.batch)
    return _plan(request, hist)


def build_ci(request: BuildRequest) -> Plan:
    """Covariance intersection of the local estimates, every step's weights in one go
    (`readouts.ci_readouts` takes all steps as one batch; on history nodes, see `_ci_nodes`)."""
    hist = local_filters(request, joint=False)
    if request.nodes is not None:
        return _plan(request, hist, _ci_nodes(request, hist))
    omega = ci_readouts(hist.steps, hist.forms, hist.mats, request.batch, request.criterion)
    return _plan(request, hist, omega)


def build_rule(request: BuildRequest, arch: Architecture) -> Plan:
    """A registered rule (`definition.Rule`) on the local filters, as the plan's readouts: at
    every step where every local has a mean, O = C and P of rule(P_j, J, criterion); NaN
    where a local is still in information form (no prior, too few measurements yet). Per run,
    the rule is applied at every step as the locals advance, to the runs' (or history nodes')
    batch."""
    rule, criterion, n = arch.rule, request.criterion, request.system.n
    assert rule is not None
    what = f"the fusion rule of {arch.name}"
    if request.batch:

        def readout(step: StepMap, form, mats, J, local_O) -> None:
            S = form.shape[0]
            if form.any():
                step.O = np.full(mats.shape[:-3] + (n, S * n), np.nan)
                step.P = np.full(mats.shape[:-3] + (n, n), np.nan)
                return
            step.O, step.P = rule(np.asarray(mats), J, criterion)
            _require_fused(form, step.P, what)

        return _plan(request, local_filters(request, joint=arch.joint, readout=readout))
    hist = local_filters(request, joint=arch.joint)
    if arch.joint:
        _checked_joints(hist)
    mats, (L, S) = hist.mats, hist.forms.shape
    O, P = np.full((L, n, S * n), np.nan), np.full((L, n, n), np.nan)
    ok = ~hist.forms.any(axis=1)
    if ok.any():
        J = np.stack(hist.joints)[ok] if arch.joint else None
        O[ok], P[ok] = rule(mats[ok], J, criterion)
    require_fused(hist.forms, P, what)
    set_readouts(hist.computed, O, P)
    return _plan(request, hist)


def _ci_nodes(request: BuildRequest, hist: LocalHistory) -> np.ndarray:
    """`ci_readouts` on history nodes: the steps' nodes (a different number at every step)
    put one after the other into a single batch per form of the locals, so that the weights
    of all of them are still one `ci_omegas` call; the readouts are then handed back to the
    steps, and the weights to the runs (M, K+1, S). Each problem is solved on its own, so
    a node gets its runs' numbers; at 20 % dropouts there are 73 % as many nodes as
    run-steps (56 % at 10 %), and the local filters run on them too."""
    nodes = request.nodes
    sizes = [len(m) for m in hist.matrices]
    S = hist.forms.shape[1]
    om_nodes: list[np.ndarray | None] = [None] * len(sizes)
    for form in np.unique(hist.forms, axis=0):
        ks = [k for k in range(len(sizes)) if (hist.forms[k] == form).all()]
        n = hist.matrices[0].shape[-1]
        mats = lanes_empty((sum(sizes[k] for k in ks), S), n, n)  # the kernels' layout
        at = 0
        for k in ks:
            mats[at : at + sizes[k]] = hist.matrices[k]
            at += sizes[k]
        holder = [StepMap(None, None, None, None)]
        om = ci_readouts(holder, form[None], mats[None], mats.shape[:1], request.criterion)
        cut = np.cumsum([sizes[k] for k in ks])[:-1]
        pieces = zip(
            ks,
            np.split(holder[0].O, cut),
            np.split(holder[0].P, cut),
            np.split(om[:, 0], cut),
            strict=True,
        )
        for k, O, P, w in pieces:
            hist.steps[k].O, hist.steps[k].P = O, P
            om_nodes[k] = w
    M = len(nodes.index[0])
    omega = np.empty((M, len(sizes), S))
    for k, w in enumerate(om_nodes):
        omega[:, k] = w[nodes.index[k]]
    return omega


# ---------------------------------------------------------------------------------------------
# The fusion rules of `readouts` for per-run plans, one step at a time as the local filters
# advance (`StepReadout`), with the batch kernels. The shared path keeps `readouts`.


def _msc_step(
    step: StepMap, form: np.ndarray, mats: np.ndarray, J: None, local_O: np.ndarray
) -> None:
    """`readouts.msc_readouts`: P^-1 = sum_j Y_j, x = P sum_j W_j s_j."""
    Ys, Ws = (a[0] for a in local_infos(form[None], mats[None]))
    Y = Ys[..., 0, :, :]
    for j in range(1, Ys.shape[-3]):
        Y = Y + Ys[..., j, :, :]
    require_finite(Y, "the fused information sum_j P_j^-1")
    P = inv_or_nan(Y)
    _require_fused(form, P, "Millman's formula")
    step.O, step.P = stack_cols(mm(P[..., None, :, :], Ws)), P


def _require_fused(form: np.ndarray, P: np.ndarray, rule: str) -> None:
    """`readouts.require_fused` for one step."""
    if not form.any() and not all_finite(P):
        raise NumericalError(
            f"{rule} gives no estimate although every local filter has one (their "
            "informations are beyond the float range)"
        )


def _avg_step(
    step: StepMap, form: np.ndarray, mats: np.ndarray, J: np.ndarray, local_O: np.ndarray
) -> None:
    """`readouts.avg_readouts`: equal weights I/S on the local means, P = M_sigma J M_sigma^T.
    O stays shared by the runs while every local's readout is (a mean: O_j = I)."""
    S, n = form.shape[0], local_O.shape[-1]
    O = stack_cols(local_O) / S
    Msig = mm(O, signs(tuple(form.tolist()), n))
    step.O, step.P = O, sym(mm(mm(Msig, J), mT(Msig)))


@dataclass
class GmfStep:
    """`readouts.gmf_readouts`. With every local in mean form, the constrained least squares
    of eqs. (5)-(7) has the closed form C = (E^T J^-1 E)^-1 E^T J^-1 (E = [I; ...; I]) when J
    is positive definite: one Cholesky solve per run. Where J is (nearly) singular (two locals
    with the same error: the paper's identical sensors share the prior's velocity error until
    their gains differ), and at steps with a local in information form, the minimum-norm KKT
    solution of the shared path, `gmf_weight_matrix`, once per distinct measurement history
    (runs with the same history so far have the same J, to the last bit)."""

    n: int
    present: np.ndarray | None  # (M, K+1, m) for runs not grouped by history, else None
    k: int = 0

    def __call__(
        self, step: StepMap, form: np.ndarray, mats: np.ndarray, J: np.ndarray, local_O
    ) -> None:
        n = self.n
        history = None if self.present is None else self.present[:, : self.k + 1]
        self.k += 1
        if form.any():
            sign = signs(tuple(form.tolist()), n)
            D = bc(step.D, J.shape[:-2] + step.D.shape[-2:])
            step.O, step.P = _per_history(
                lambda Js, D: _gmf_each(Js, n, D), history, mm(mm(sign, J), sign), D
            )
            return
        S = J.shape[-1] // n
        E = np.tile(np.eye(n), (S, 1))
        X, ok = solve_spd_or_flag(J, E, GMF_PIVOT_RTOL)  # J^-1 E
        big = np.abs(X).max(axis=(-2, -1)) * np.abs(J).max(axis=(-2, -1))
        ok &= big < GMF_MAX_GROWTH
        if not ok.all():
            X[~ok] = E  # placeholders, replaced below
        W = X[..., :n, :]
        for i in range(1, S):
            W = W + X[..., i * n : (i + 1) * n, :]
        C = mm(spd_inv(W), mT(X))
        P = sym(mm(mm(C, J), mT(C)))
        ok &= np.isfinite(P).all(axis=(-2, -1))  # e.g. subnormal noise variances
        if not ok.all():
            bad = np.flatnonzero(~ok)
            runs = None if history is None else history[bad]
            C[bad], P[bad] = _per_history(lambda Js: _gmf_each(Js, n), runs, J[bad])
        step.O, step.P = C, P


#: A Cholesky pivot of J below this times its diagonal entry, or |J^-1 E| |J| beyond
#: GMF_MAX_GROWTH, sends a GMF problem to the least-squares solution of the shared path:
#: the closed form would amplify rounding by about that much, and where J is singular to
#: working precision the weights are not unique (least squares takes the smallest). The
#: paper's example stays at pivots above 1e-3 and growths below 200.
GMF_PIVOT_RTOL = 1e-6
GMF_MAX_GROWTH = 1e6
#: At most this many GMF problems are solved one by one (below).
GMF_ONE_BY_ONE = 256


def _gmf_each(J: np.ndarray, n: int, D: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`gmf_weight_matrix` for a batch of J (and D), each solved on its own as the shared path
    solves its one J (lstsq, SVD): near a singular J the weights are not unique and the
    batched pseudo-inverse picks other ones, differing in the means by ~1e-10. Many problems
    go through the batched call."""
    if len(J) > GMF_ONE_BY_ONE:
        return gmf_weight_matrix(J, n, D)
    outs = [gmf_weight_matrix(J[i], n, None if D is None else D[i]) for i in range(len(J))]
    C = np.stack([o[0] for o in outs]) if outs else np.empty(J.shape[:1] + (n, J.shape[-1]))
    P = np.stack([o[1] for o in outs]) if outs else np.empty(J.shape[:1] + (n, n))
    return C, P


def _per_history(
    rule: Callable[..., tuple[np.ndarray, np.ndarray]],
    history: np.ndarray | None,
    *args: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """rule(*args) for a batch of runs, computed once per distinct measurement history
    (history: (runs, steps so far, m) presence masks) and handed to every run that has it;
    rule(*args) itself for history nodes (history None), distinct already."""
    if history is None:
        return rule(*args)
    keys = np.packbits(history.reshape(len(history), -1), axis=1)
    keys = np.ascontiguousarray(keys).view(np.dtype((np.void, keys.shape[1]))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    outs = rule(*(a[first] for a in args))
    return tuple(o[inverse] for o in outs)
