"""Track-to-track fusion: local KFs without feedback, one per sensor, and a fusion rule applied to
their estimates at every step (the readout x_hat = O s, P of the plan):

* MSC      Millman's formula assuming independent local errors, eqs. (32)-(34);
* MSC-GMF  the generalised Millman formula with the exact cross-covariances, eqs. (6)-(7), (35);
* CI       covariance intersection ("safe fusion", Gustafsson-Hendeby);
* AVG      the plain average of the local means with the covariance it really has, eq. (4).

The local filters' joint error covariance follows eq. (35), extended by K_i R_ij K_j^T for
correlated sensor noise and by information-form errors for filters started without a prior.
The local filters run as one stack (`KalmanStack` on `Rows.per_sensor`); the fusion rules, which
do not feed back, are evaluated for all steps together after the recursion (`readouts`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..linalg import bc, mT, require_finite, stack_diag, stack_rows, sym
from .filters import KalmanStack, Rows, Steady, fill
from .plan import BuildRequest, Plan, StepMap
from .readouts import avg_readouts, ci_readouts, gmf_readouts, msc_readouts


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
        return np.stack(self.matrices)

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
        J = bc(np.kron(np.ones((S, S)), system.prior.cov), batch + (S * n, S * n)).copy()
    else:
        J = np.zeros(batch + (S * n, S * n))
    stack = batch + (S, n, n)
    # When every local is in covariance form they all predict with F and the full process
    # noise: Phi and Gam of eq. (35), and the noise term, are then the same at every step.
    Phi_cov = stack_diag(bc(system.F, (S, n, n)))
    Gam_cov = D_cov = stack_rows(locs.I)  # and D_j = I
    GQG_cov = Gam_cov @ GQG @ mT(Gam_cov)
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
                    GQG_cov = Gam_cov @ GQG @ mT(Gam_cov)
            if not first and st.Phi is locs.F:  # every local predicted in covariance form
                J = Phi_cov @ J @ mT(Phi_cov) + GQG_cov
            elif not first:
                Phi = stack_diag(bc(st.Phi, stack))
                Gam = stack_rows(bc(st.Gam, stack))
                J = Phi @ J @ mT(Phi) + Gam @ GQG @ mT(Gam)
            Psi = stack_diag(bc(st.Psi, stack))
            Lam = stack_rows(st.Lam)
            _, Rk = everything.masked(present[..., k, :])
            J = sym(Psi @ J @ mT(Psi) + Lam @ Rk @ mT(Lam))
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
    return LocalHistory(steps, np.stack(forms), np.stack(mats), joints, readouts, locs.s0, locs.D0)


def _plan(request: BuildRequest, hist: LocalHistory, omega: np.ndarray | None = None) -> Plan:
    batch = request.batch
    return Plan(request.name, hist.s0, hist.steps, per_run=bool(batch), D0=hist.D0, omega=omega)


def build_msc(request: BuildRequest) -> Plan:
    """Millman's formula on the local estimates, eqs. (32)-(34)."""
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
    hist = local_filters(request, joint=True)
    _checked_joints(hist)
    gmf_readouts(hist.computed, hist.forms, hist.joints, request.system.n)
    return _plan(request, hist)


def build_avg(request: BuildRequest) -> Plan:
    """The plain average of the local means and its true covariance, eq. (4)."""
    hist = local_filters(request, joint=True)
    _checked_joints(hist)
    avg_readouts(hist.computed, hist.forms, hist.joints, hist.readouts, request.batch)
    return _plan(request, hist)


def build_ci(request: BuildRequest) -> Plan:
    """Covariance intersection of the local estimates, every step's weights in one go."""
    hist = local_filters(request, joint=False)
    omega = ci_readouts(hist.steps, hist.forms, hist.mats, request.batch, request.criterion)
    return _plan(request, hist, omega)
