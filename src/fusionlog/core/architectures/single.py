"""One Kalman filter on a set of sensors: the centralised KF (CKF, eqs. 29-31, all sensors
stacked as in eq. 30) and the single-sensor KF (SKF, one sensor's rows of z_k)."""

from __future__ import annotations

import numpy as np

from ..model import System
from .filters import KalmanStack, Rows, Steady, fill
from .plan import BuildRequest, Plan, StepMap


def filter_plan(
    request: BuildRequest, system: System, rows: np.ndarray
) -> tuple[Plan, list[np.ndarray | None]]:
    """One KF on the components `rows` of z_k: its plan, and for every step the information
    matrix the filter carries while it is still in information form (None once it has a
    covariance), which the smoother's fusion needs."""
    present = request.present
    batch = request.batch
    Rs = None if system.Rs is None else system.Rs[:, rows][:, :, rows]
    kf = KalmanStack(system, Rows.of(system, rows, system.R[np.ix_(rows, rows)], Rs), batch)
    steps = []
    infos: list[np.ndarray | None] = []
    steady = Steady(present, system)
    K1 = request.horizon
    for k in range(K1):
        st = kf.step(request.mask(k), k, request.begin(k))
        steps.append(StepMap(st.T, st.U, st.O, st.P, st.D))
        infos.append(kf.mat if kf.any_info else None)
        if not kf.any_info and steady.reached(kf.mat, k=k):
            fill(steps, K1)
            fill(infos, K1)
            break
    plan = Plan(request.name, kf.s0, steps, per_run=bool(batch), D0=kf.D0)
    plan.nodes = request.node_index
    return plan, infos


def build_ckf(request: BuildRequest) -> Plan:
    """Centralised KF on every sensor, eqs. (29)-(31)."""
    system = request.system
    return filter_plan(request, system, np.arange(system.m))[0]


def build_skf(request: BuildRequest) -> Plan:
    """KF on one sensor (`request.sensor`) only."""
    system = request.system
    j = system.sensor_index(request.sensor)
    return filter_plan(request, system, np.arange(system.m)[system.sensor_slices[j]])[0]
