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

from dataclasses import dataclass

import numpy as np

from ..fusion import gmf_weight_matrix
from ..linalg import (
    all_finite,
    bc,
    inv_or_nan,
    kernels_for,
    lanes_copy,
    many_matrices,
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
)
from .filters import KalmanStack, Rows, Steady, fill
from .plan import BuildRequest, Plan, StepMap
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
    x_j = O_j s_j."""

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


def local_filters(request: BuildRequest, joint: bool) -> LocalHistory:
    """Run the stack of local KFs over the horizon; with `joint`, carry eq. (35) along."""
    system, present, batch = request.system, request.present, request.batch
    n, m = system.n, system.m
    S = len(system.sensors)
    GQG = system.GQG
    locs = KalmanStack(system, Rows.per_sensor(system), batch)
    everything = Rows.of(system, np.arange(m), system.R)  # masked per step for eq. (35)
    if system.prior is not None:
        J = bc(np.kron(np.ones((S, S)), system.prior.cov), batch + (S * n, S * n))
    else:
        J = bc(np.zeros((S * n, S * n)), batch + (S * n, S * n))
    J = lanes_copy(J) if many_matrices(batch) else J.copy()
    stack = batch + (S, n, n)
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
        request.step = k
        first = k == 0
        st = locs.step(present[..., k, :], k)
        if joint:
            if not first and not system.time_invariant:
                GQG = system.GQG_at(k)
                if st.Phi is locs.F:
                    Phi_cov = stack_diag(bc(locs.F, (S, n, n)))
                    GQG_cov = mm(mm(Gam_cov, GQG), mT(Gam_cov))
            if not first and st.Phi is locs.F:  # every local predicted in covariance form
                J = mm(mm(Phi_cov, J), mT(Phi_cov)) + GQG_cov
            elif not first:
                Phi = stack_diag(bc(st.Phi, stack))
                Gam = stack_rows(bc(st.Gam, stack))
                J = mm(mm(Phi, J), mT(Phi)) + mm(mm(Gam, GQG), mT(Gam))
            Psi = stack_diag(bc(st.Psi, stack))
            Lam = stack_rows(st.Lam)
            _, Rk = everything.masked(present[..., k, :])
            J = sym(mm(mm(Psi, J), mT(Psi)) + mm(mm(Lam, Rk), mT(Lam)))
        T = stack_diag(bc(st.T, stack))
        # A local's state s_j is D_j x + sigma_j with sigma_j = -g_j (mean form: s = x_hat,
        # g = x - x_hat) or +g_j (information form: s = y, g = y - Y x); J is cov(g).
        D = D_cov if st.D is locs.I else stack_rows(bc(st.D, stack))  # D_j = I: mean form
        steps.append(StepMap(T, stack_rows(st.U), None, None, D))  # O, P: set by a readout
        forms.append(locs.info)
        mats.append(locs.mat)
        joints.append(J)
        readouts.append(st.O)
        if not locs.any_info and steady.reached(J if joint else locs.mat):
            fill(steps, K1)
            break
    request.step = None  # the readouts process every step at once
    return LocalHistory(steps, np.stack(forms), mats, joints, readouts, locs.s0, locs.D0)


def _plan(request: BuildRequest, hist: LocalHistory, omega: np.ndarray | None = None) -> Plan:
    batch = request.batch
    return Plan(request.name, hist.s0, hist.steps, per_run=bool(batch), D0=hist.D0, omega=omega)


def build_msc(request: BuildRequest) -> Plan:
    """Millman's formula on the local estimates, eqs. (32)-(34)."""
    hist = local_filters(request, joint=False)
    if request.batch:
        _msc_per_run(hist)
    else:
        msc_readouts(hist.computed, hist.forms, hist.mats)
    return _plan(request, hist)


def _checked_joints(hist: LocalHistory) -> None:
    """J of eq. (35) is only multiplied in the recursion, so an overflow there (once non-finite,
    it stays so) is looked for once, before a fusion rule solves with it."""
    if not all(all_finite(J) for J in hist.joints):
        require_finite(
            np.stack(hist.joints), "the local filters' joint error covariance", per_step=True
        )


def build_msc_gmf(request: BuildRequest) -> Plan:
    """The generalised Millman formula with the exact cross-covariances, eqs. (6)-(7), (35)."""
    hist = local_filters(request, joint=True)
    _checked_joints(hist)
    if request.batch:
        _gmf_per_run(hist, request.system.n)
    else:
        gmf_readouts(hist.computed, hist.forms, hist.joints, request.system.n)
    return _plan(request, hist)


def build_avg(request: BuildRequest) -> Plan:
    """The plain average of the local means and its true covariance, eq. (4)."""
    hist = local_filters(request, joint=True)
    _checked_joints(hist)
    if request.batch:
        _avg_per_run(hist)
    else:
        avg_readouts(hist.computed, hist.forms, hist.joints, hist.readouts, request.batch)
    return _plan(request, hist)


def build_ci(request: BuildRequest) -> Plan:
    """Covariance intersection of the local estimates, every step's weights in one go."""
    hist = local_filters(request, joint=False)
    omega = ci_readouts(hist.steps, hist.forms, hist.mats, request.batch, request.criterion)
    return _plan(request, hist, omega)


# ---------------------------------------------------------------------------------------------
# The fusion rules of `readouts` for per-run plans: the same equations with the batch kernels,
# one step at a time (the shared path's readouts are not changed by these).


def _msc_per_run(hist: LocalHistory) -> None:
    """`readouts.msc_readouts`: P^-1 = sum_j Y_j, x = P sum_j W_j s_j."""
    Ys, Ws = local_infos(hist.forms, hist.mats)
    Y = Ys[..., 0, :, :]
    for j in range(1, Ys.shape[-3]):
        Y = Y + Ys[..., j, :, :]
    require_finite(Y, "the fused information sum_j P_j^-1", per_step=True)
    P = inv_or_nan(Y)
    require_fused(hist.forms, P, "Millman's formula")
    set_readouts(hist.computed, stack_cols(mm(P[..., None, :, :], Ws)), P)


def _avg_per_run(hist: LocalHistory) -> None:
    """`readouts.avg_readouts`: equal weights I/S on the local means, P = M_sigma J M_sigma^T.
    O stays shared by the runs while every local's readout is (a mean: O_j = I)."""
    S, n = hist.forms.shape[1], hist.readouts[0].shape[-1]
    for st, form, J, local_O in zip(
        hist.computed, hist.forms, hist.joints, hist.readouts, strict=True
    ):
        O = stack_cols(local_O) / S
        Msig = mm(O, signs(tuple(form.tolist()), n))
        st.O, st.P = O, sym(mm(mm(Msig, J), mT(Msig)))


def _gmf_per_run(hist: LocalHistory, n: int) -> None:
    """`readouts.gmf_readouts`. With every local in mean form, the constrained least squares
    of eqs. (5)-(7) has the closed form C = (E^T J^-1 E)^-1 E^T J^-1 (E = [I; ...; I]) when J
    is positive definite: one Cholesky solve per run. Runs whose J is (nearly) singular (two
    locals with the same error, e.g. both missed every measurement so far and share the
    prior), and steps with a local in information form, take `gmf_weight_matrix`, the
    minimum-norm KKT solution of the shared path."""
    for st, form, J in zip(hist.computed, hist.forms, hist.joints, strict=True):
        if form.any() or not kernels_for(J):
            sign = signs(tuple(form.tolist()), n)
            Js = mm(mm(sign, J), sign) if form.any() else J
            st.O, st.P = gmf_weight_matrix(Js, n, st.D if form.any() else None)
            continue
        S = J.shape[-1] // n
        E = np.tile(np.eye(n), (S, 1))
        X, ok = solve_spd_or_flag(J, E)  # J^-1 E
        if not ok.all():
            X[~ok] = E  # placeholders, replaced below
        W = X[..., :n, :]
        for i in range(1, S):
            W = W + X[..., i * n : (i + 1) * n, :]
        C = mm(spd_inv(W), mT(X))
        P = sym(mm(mm(C, J), mT(C)))
        ok &= np.isfinite(P).all(axis=(-2, -1))  # e.g. subnormal noise variances
        if not ok.all():
            bad = np.nonzero(~ok)
            C[bad], P[bad] = gmf_weight_matrix(J[bad], n)
        st.O, st.P = C, P
