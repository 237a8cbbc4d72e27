"""Hierarchical KF with feedback (HKF), eqs. (36)-(40)."""

from __future__ import annotations

import numpy as np

from ..kalman import gain, joseph
from ..linalg import bc, block_diag, require_finite, spd_inv_scaled, sum_after, sym
from ..model import System
from .filters import KalmanStack, Rows, Steady, fill
from .plan import BuildRequest, Plan, StepMap


def blockdiag_R(system: System) -> np.ndarray:
    """R of eq. (31) without cross-covariances: what architectures that assume independent
    sensor noise (HKF's equivalent measurements) believe."""
    return block_diag([s.R for s in system.sensors])


def build_hkf(request: BuildRequest) -> Plan:
    """Hierarchical KF with feedback, eqs. (36)-(40).

    Each local KF j restarts from the fused prediction (38), updates with its own sensor, and the
    fusion centre adds the equivalent measurements P_j^-1 x_j - P^-1_pred x_pred (36)-(37). The
    S local updates are one batched computation on the stacked sensors (`Rows.per_sensor`).
    The fusion inverts covariances and informations at every step: `spd_inv_scaled` keeps
    them accurate when sensors are far more precise than the prediction (R = 1e-300).
    """
    system, present, batch = request.system, request.present, request.batch
    n, m = system.n, system.m
    S = len(system.sensors)
    F, GQG = system.F, system.GQG
    eye = np.eye(n)
    # Before a covariance exists (no prior), local equivalent measurements are just
    # H_j^T R_j^-1 H_j: the fused information filter on block-diagonal R is exactly that.
    front = KalmanStack(system, Rows.of(system, np.arange(m), blockdiag_R(system)), batch)
    sensors = Rows.per_sensor(system)
    steps = []
    P = None
    steady = Steady(present)
    K1 = request.horizon
    for k in range(K1):
        request.step = k
        first = k == 0
        if front.any_info:
            st = front.step(present[..., k, :], first)
            steps.append(StepMap(st.T, st.U, st.O, st.P, st.D))
            P = front.mat
            continue
        if first:
            Pp, Tp = front.mat, eye
        else:
            Pp, Tp = sym(F @ P @ F.T + GQG), F
            require_finite(Pp, "the predicted covariance")
        Yp = spd_inv_scaled(Pp)
        Hj, Rj = sensors.masked(present[..., k, :])  # batch + (S, r, .)
        Ppj = Pp[..., None, :, :]  # every local starts from the fused prediction
        Kj = gain(Ppj, Hj, Rj)
        IKH = eye - Kj @ Hj
        Yj = spd_inv_scaled(joseph(Ppj, Kj, Hj, Rj, IKH))
        Yf = sum_after((1 - S) * Yp, Yj)
        Tacc = sum_after((1 - S) * Yp, Yj @ IKH)
        # Each sensor's gain sits in its own columns of z_k, zero elsewhere: the sum is exact.
        U = (Yj @ Kj @ sensors.E).sum(axis=-3)
        P = spd_inv_scaled(Yf)
        require_finite(P, "the fused covariance")
        steps.append(StepMap(P @ Tacc @ Tp, P @ U, bc(eye, P.shape), P, eye))
        if steady.reached(P):
            fill(steps, K1)
            break
    return Plan(request.name, front.s0, steps, per_run=bool(batch), D0=front.D0)
