"""Track-to-track rules that read the locals' joint error covariance (MSC-GMF, AVG) where
correlated sensors' readings of one instant arrive apart (reprocess, neglect; see
`core.latency` and `core.latency_corr`).

Each local filter fuses one sensor on the stacked model (`latency_stacked.stacked_system`):
its readings of an instant arrive together, so it is the Kalman filter of its sensor. But
sensor i's reading of instant t may enter local i at k1 and sensor j's, correlated with it,
local j at k2 != k1: on the stacked model their noises are then correlated across time, which
eq. (35)'s recursion (`track_to_track.local_filters`, white noise pairing the noises entering
two locals at one instant) does not see. On the measurements as taken the noise is white
with the joint R of each instant, so, as for the retrodicting locals (`retrodict_fused`), J
comes from the plan's affine maps: the locals wrapped to read z as taken (`latency_stacked.
wrap`, their state s_k = [the stacked locals; the last W readings]) and y_k = [x_k; s_k],

    y_k = A_k y_{k-1} + B_k w_k + [0; U_k] v_k,   A = [[F, 0], [U H F, T]],  B = [I; U H],

cov(v_k) the joint R (its cross-sensor blocks included), J = E cov(y) E^T for the errors
e_j = x_k - O_j s_j of the locals' current blocks, computed on [x_k; s_k - D_k x_k] (`wrap`'s
error form D), whose terms stay of the size of the errors. The locals are exact Kalman filters, so
J's diagonal blocks are the covariances they report.
"""

from __future__ import annotations

import numpy as np

from .architectures import BuildRequest, Plan, StepMap, definition
from .architectures.track_to_track import local_filters
from .latency_stacked import wrap
from .linalg import mT, numerical_errors, sym
from .model import System
from .retrodict_fused import _error_moments, _rule

__all__ = ["joint_fused_plan"]


def joint_fused_plan(
    system: System,
    stacked: System,
    arch: str,
    present: np.ndarray,
    slots: np.ndarray,
    W: int,
    criterion: str,
) -> Plan:
    """The track-to-track architecture `arch` (one local per sensor on the `stacked` model of
    `system`, mask `present` (K+1, m~) or per run (M, K+1, m~)) on z as taken (`wrap` with
    `slots`, window W), its rule fed the locals' J from the affine maps (module docstring)."""
    n, m = system.n, system.m
    S, N = len(system.sensors), stacked.n
    arch_def = definition(arch)
    request = BuildRequest(stacked, arch, present, None, criterion)  # per run: no nodes

    def where() -> str:
        step = "" if request.step is None else f", step {request.step}"
        return f"architecture {arch}{step}"

    with numerical_errors(where):
        hist = local_filters(request, joint=False)
    batch = request.batch
    # wrap the locals' maps only (their readout is the rule's, set below)
    held: dict[int, StepMap] = {}
    for st in hist.steps:
        if id(st) not in held:
            O = np.zeros(batch + (n, S * N))
            held[id(st)] = StepMap(st.T, st.U, O, np.zeros((n, n)), st.D)
    steps = [held[id(st)] for st in hist.steps]
    inner = Plan(arch, hist.s0, steps, per_run=bool(batch), D0=hist.D0)
    wrapped = wrap(inner, slots, m, W, n, system=system)  # with its error form D
    dw = len(wrapped.s0)
    Ol = np.zeros((S * n, dw))  # the locals' current blocks x_hat_j = O_j s
    for j in range(S):
        Ol[j * n : (j + 1) * n, j * N : j * N + n] = np.eye(n)
    E = np.zeros((S * n, n + dw))  # e_j = (I - O_j D_j) x_k - O_j zeta_j, zeta = s - D x
    E[:, n:] = -Ol
    H = system.linear_measurement()
    assert system.prior is not None
    mats, L = hist.mats, len(hist.forms)
    steps, omegas, cov, D_prev = [], [], None, wrapped.D0
    for k, st in enumerate(wrapped.steps):
        request.step = k
        cov = _error_moments(system, k, st, D_prev, cov, system.prior.cov, H)
        D_prev = st.D
        Ek = np.broadcast_to(E, st.D.shape[:-2] + E.shape).copy()
        Ek[..., :n] = np.tile(np.eye(n), (S, 1)) - Ol @ st.D
        J = sym(Ek @ cov @ mT(Ek))
        Ploc = np.ascontiguousarray(mats[min(k, L - 1)][..., :n, :n])
        with numerical_errors(where):
            C, Pf, w = _rule(arch_def, Ploc, J, criterion)
        omegas.append(w)
        steps.append(StepMap(st.T, st.U, C @ Ol, Pf, st.D))
    omega = None
    if any(w is not None for w in omegas):
        omega = np.stack([np.broadcast_to(w, batch + (S,)) for w in omegas], axis=-2)
    # plan.system stays None: the exact analysis keeps the true state's terms
    # (`moments.coupling`), so it is exact with any D; D (`wrap`'s) only conditions it
    plan = Plan(arch, wrapped.s0, steps, per_run=bool(batch), D0=wrapped.D0)
    plan.complete, plan.omega = False, omega
    return plan
