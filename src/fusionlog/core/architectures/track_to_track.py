"""Track-to-track fusion: local KFs without feedback, one per sensor, and a registered fusion rule
(`definition.Rule`: MSC, MSC-GMF, CI, AVG in `rules`, ICI, ...) applied to their estimates at
every step, as the plan's readout x_hat = O s, P.

The local filters' joint error covariance follows eq. (35), extended by K_i R_ij K_j^T for
correlated sensor noise and by information-form errors for filters started without a prior.
The local filters run as one stack (`KalmanStack` on `Rows.per_sensor`). On a shared mask the
rule, which does not feed back, is applied to all computed steps together after the recursion
(one call per combination of the locals' forms); per run it is applied at every step as the
locals advance, to the runs' (or history nodes') batch: keeping every step's J would cost more
memory than the plan itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...errors import NumericalError
from ..linalg import (
    all_finite,
    apply_shared,
    bc,
    buffer,
    lanes,
    lanes_copy,
    mm,
    mT,
    require_finite,
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


@dataclass
class LocalHistory:
    """The local filters' recursion: the plan's steps (readouts O, P still to be set) and,
    after each computed step (L of them; the steps after repeat the last), the locals' forms
    (L, S) (True: information form), their matrices (covariance, or information in information
    form) and their joint error covariance J of eq. (35) (when asked for). With a per-step
    readout (`local_filters`), the matrices and J are handed to it and not kept (empty
    lists)."""

    steps: list[StepMap]
    forms: np.ndarray
    matrices: list[np.ndarray]
    joints: list[np.ndarray]
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
#: J of eq. (35) or None).
StepReadout = Callable[[StepMap, np.ndarray, np.ndarray, np.ndarray | None], None]


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
    forms, mats, joints = [], [], []
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
            readout(step, locs.info, locs.mat, J if joint else None)
        else:
            mats.append(locs.mat)
            joints.append(J)
        if not locs.any_info and steady.reached(J if joint else locs.mat, k=k):
            fill(steps, K1)
            break
    request.step = None  # the readouts process every step at once
    return LocalHistory(steps, np.stack(forms), mats, joints, locs.s0, locs.D0)


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


def _plan(request: BuildRequest, hist: LocalHistory, omega: np.ndarray | None) -> Plan:
    batch = bool(request.batch)
    plan = Plan(request.name, hist.s0, hist.steps, per_run=batch, D0=hist.D0, omega=omega)
    plan.nodes = request.node_index
    return plan


def _checked_joints(hist: LocalHistory) -> None:
    """J of eq. (35) is only multiplied in the recursion, so an overflow there (once non-finite,
    it stays so) is looked for once, before a fusion rule solves with it."""
    require_finite(
        np.stack(hist.joints), "the local filters' joint error covariance", per_step=True
    )


def build_rule(request: BuildRequest, arch: Architecture) -> Plan:
    """The registered rule of `arch` (`definition.Rule`) on the local filters, as the plan's
    readouts: at every step O = C and P of the rule on the locals' matrices and J; where a
    local is still in information form, the rule's information form (`arch.information`) or
    NaN. Shared: the computed steps in one call per combination of forms. Per run: at every
    step as the locals advance, on the runs' (or history nodes') batch."""
    n = request.system.n
    fuse = _applied(arch, request.criterion)
    omegas: list[np.ndarray | None] = []  # each computed step's, when the rule has some
    if request.batch:

        def readout(step: StepMap, form: np.ndarray, mats: np.ndarray, J) -> None:
            found: dict[str, np.ndarray] = {}
            step.O, step.P = fuse(form, mats, J, found)
            _require_fused(form[None], step.P[None], arch.name, per_step=False)
            omegas.append(found.get("omega"))

        hist = local_filters(request, joint=arch.joint, readout=readout)
        return _plan(request, hist, _omega(request, hist, omegas))
    hist = local_filters(request, joint=arch.joint)
    if arch.joint:
        _checked_joints(hist)
    mats, (L, S) = hist.mats, hist.forms.shape
    joints = np.stack(hist.joints) if arch.joint else None
    O, P = np.empty((L, n, S * n)), np.empty((L, n, n))
    omegas = [None] * L
    for form in np.unique(hist.forms, axis=0):
        ks = np.flatnonzero((hist.forms == form).all(axis=1))
        found: dict[str, np.ndarray] = {}
        try:
            O[ks], P[ks] = fuse(form, mats[ks], None if joints is None else joints[ks], found)
        except NumericalError:  # name the step: the first that fails on its own
            for k in ks:
                request.step = int(k)
                fuse(form, mats[k], None if joints is None else joints[k], {})
            raise
        finally:
            request.step = None
        if "omega" in found:
            for i, k in enumerate(ks):
                omegas[k] = found["omega"][i]
    _require_fused(hist.forms, P, arch.name)
    for st, Ok, Pk in zip(hist.computed, O, P, strict=True):
        st.O, st.P = Ok, Pk
    return _plan(request, hist, _omega(request, hist, omegas))


def _omega(
    request: BuildRequest, hist: LocalHistory, omegas: list[np.ndarray | None]
) -> np.ndarray | None:
    """`Plan.omega`, batch + (K+1, S), from each computed step's weights (None where the rule
    gave none: NaN), the steps after the computed ones repeating the last; per run on
    history nodes, each run's node's."""
    if all(w is None for w in omegas):
        return None
    K1, S = request.horizon, hist.forms.shape[1]
    nodes = request.node_index
    batch = request.batch if nodes is None else (len(nodes[0]),)
    omega = np.full(batch + (K1, S), np.nan)
    for k in range(K1):
        w = omegas[min(k, len(omegas) - 1)]
        if w is not None:
            omega[..., k, :] = w if nodes is None else w[nodes[k]]
    return omega


def _applied(arch: Architecture, criterion: str) -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """(forms (S,), the locals' matrices, J, found) -> (C, P) of the rule of `arch` on that
    batch: its information form where a local has one, NaN where the rule has none; a C that
    is the same for the whole batch (a broadcast) kept once."""
    rule = arch.rule
    assert rule is not None

    def fuse(form: np.ndarray, mats: np.ndarray, J: np.ndarray | None, found: dict):
        if arch.information:
            C, P = rule(mats, J, criterion, forms=form, found=found)
        elif not form.any():
            C, P = rule(mats, J, criterion)
        else:
            S, n = mats.shape[-3], mats.shape[-1]
            return (
                np.full(mats.shape[:-3] + (n, S * n), np.nan),
                np.full(mats.shape[:-3] + (n, n), np.nan),
            )
        while C.ndim > 2 and C.strides[0] == 0:  # the same weights for every problem
            C = C[0]
        return C, P

    return fuse


def _require_fused(forms: np.ndarray, P: np.ndarray, name: str, per_step: bool = True) -> None:
    """Refuse a fused covariance P ((L,) + batch + (n, n)) that is undefined at a step where
    every local filter has an estimate of its own (forms (L, S) all False): the rule has an
    answer there, so NaN means its numbers left the float range. `per_step`: the message names
    the step (else the one being built names itself)."""
    if all_finite(P):
        return
    every = ~forms.any(axis=1)
    bad = every & ~np.isfinite(P).reshape(len(P), -1).all(axis=1)
    if bad.any():
        step = f"step {int(np.argmax(bad))}: " if per_step else ""
        raise NumericalError(
            f"{step}the fusion rule of {name} gives no estimate although every local filter "
            "has one (their informations are beyond the float range)"
        )
