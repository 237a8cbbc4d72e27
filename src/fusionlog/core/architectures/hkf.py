"""Hierarchical KF with feedback (HKF), eqs. (36)-(40)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..kalman import gain, joseph
from ..linalg import (
    all_finite,
    bc,
    block_diag,
    mm,
    require_finite,
    spd_inv,
    spd_inv_scaled,
    sum_after,
    sym,
    take_runs,
)
from ..model import System
from .filters import KalmanStack, Rows, Steady, fill, wide_range
from .plan import BuildRequest, Plan, StepMap


def blockdiag_R(system: System) -> np.ndarray:
    """R of eq. (31) without cross-covariances: what architectures that assume independent
    sensor noise (HKF's equivalent measurements) believe."""
    return block_diag([s.R for s in system.sensors])


def independent_noise(system: System) -> System:
    """The system with the noise HKF believes: its sensors' own R, no cross-covariances (the
    per-instant Rs cut likewise); HKF's late readings are retrodicted on it
    (`core.retrodict_fused`)."""
    Rs = None
    if system.Rs is not None:
        Rs = np.zeros_like(system.Rs)
        for sl in system.sensor_slices:
            Rs[:, sl, sl] = system.Rs[:, sl, sl]
    return dataclasses.replace(system, cross_R={}, Rs=Rs)


def build_hkf(request: BuildRequest) -> Plan:
    """Hierarchical KF with feedback, eqs. (36)-(40).

    Each local KF j restarts from the fused prediction (38), updates with its own sensor, and the
    fusion centre adds the equivalent measurements P_j^-1 x_j - P^-1_pred x_pred (36)-(37). The
    S local updates are one batched computation on the stacked sensors (`Rows.per_sensor`).
    The fusion inverts covariances and informations at every step; when the model's noise
    levels span many orders of magnitude (R = 1e-300 against Q = 0.05) they go through
    `spd_inv_scaled`, which keeps them accurate (decided once per plan: the test costs more
    than the inversion of a 2 x 2 matrix).
    """
    system, present, batch = request.system, request.present, request.batch
    n, m = system.n, system.m
    S = len(system.sensors)
    eye = np.eye(n)
    inv = spd_inv_scaled if wide_range(system) else spd_inv
    # Before a covariance exists (no prior), local equivalent measurements are just
    # H_j^T R_j^-1 H_j: the fused information filter on block-diagonal R is exactly that.
    Rs = independent_noise(system).Rs  # per instant, without the cross-covariances
    front = KalmanStack(system, Rows.of(system, np.arange(m), blockdiag_R(system), Rs), batch)
    sensors = Rows.per_sensor(system)
    steps = []
    P = None
    steady = Steady(present, system)
    K1 = request.horizon
    for k in range(K1):
        parent = request.begin(k)  # on history nodes: each node continues its parent's
        first = k == 0
        if front.any_info:
            st = front.step(request.mask(k), k, parent)
            steps.append(StepMap(st.T, st.U, st.O, st.P, st.D))
            P = front.mat
            continue
        if parent is not None:
            P = take_runs(front.mat if first else P, parent)
        if first:
            Pp, Tp = front.mat if parent is None else P, eye
        else:
            F, GQG = system.F_at(k), system.GQG_at(k)
            Pp, Tp = sym(mm(mm(F, P), F.T) + GQG), F
        Yp = inv(Pp, what="the predicted covariance")
        Hj, Rj = sensors.masked(request.mask(k), k)  # batch + (S, r, .)
        Ppj = Pp[..., None, :, :]  # every local starts from the fused prediction
        Kj = gain(Ppj, Hj, Rj)
        IKH = eye - mm(Kj, Hj)
        Yj = inv(joseph(Ppj, Kj, Hj, Rj, IKH), what="a local covariance")
        Yf = sum_after((1 - S) * Yp, Yj)
        Tacc = sum_after((1 - S) * Yp, mm(Yj, IKH))
        # Each sensor's gain sits in its own columns of z_k, zero elsewhere: the sum is exact.
        U = mm(mm(Yj, Kj), sensors.E).sum(axis=-3)
        P = inv(Yf, what="the fused information")
        if not all_finite(P):
            require_finite(Pp, "the predicted covariance")
            require_finite(P, "the fused covariance")
        steps.append(StepMap(mm(mm(P, Tacc), Tp), mm(P, U), bc(eye, P.shape), P, eye))
        if steady.reached(P, k=k):
            fill(steps, K1)
            break
    plan = Plan(request.name, front.s0, steps, per_run=bool(batch), D0=front.D0)
    plan.nodes = request.node_index
    return plan
