"""Fixed-interval smoother (FBS), eqs. (25)-(28): the forward KF on all sensors fused by Millman's
formula with a backward information filter started from zero information."""

from __future__ import annotations

import numpy as np

from ..linalg import bc, inv_or_nan, mm, mT, require_finite, solve, sym
from .filters import Rows, Steady
from .plan import BuildRequest, Plan, SmootherMaps, take_map
from .single import filter_plan


def build_fbs(request: BuildRequest) -> Plan:
    """Forward KF (`single.filter_plan` on every sensor), backward information filter, fusion.

    Backward filter: S^+ = S_{k+1} + H^T R^-1 H, y^+ = y_{k+1} + H^T R^-1 z_{k+1} (data at
    k+1), then back through the dynamics, S_k = F^T (I + S^+ GQG)^-1 S^+ F and
    y_k = F^T (I + S^+ GQG)^-1 y^+. Fusion with the forward filter's P: Millman's formula as
    the gain K_s = P S (I + P S)^-1 (26), P_s = (I - K_s) P (27), x_s = (I - K_s) x + P_s y_b (28).
    """
    system, present = request.system, request.present
    runs = present.shape[:-2]  # the backward filter and the fusion are per run
    fwd, fwd_infos = filter_plan(request, system, np.arange(system.m))  # maybe per node
    n = system.n
    eye = np.eye(n)
    K1 = request.horizon
    V: list[np.ndarray] = [np.zeros(0)] * K1
    L: list[np.ndarray] = [np.zeros(0)] * (K1 - 1)
    Smat: list[np.ndarray] = [np.zeros(0)] * (K1 - 1) + [np.zeros(runs + (n, n))]
    steady = Steady(present, system)
    everything = Rows.all_of(system)
    Hn = None  # the masked H of instant k + 1
    for k in range(K1 - 1, -1, -1):
        request.step = k
        if steady.enabled and k < K1 - 3 and Smat[k + 1] is Smat[k + 2]:
            V[k], L[k], Smat[k], Hn = V[k + 1], L[k + 1], Smat[k + 1], None
            continue
        Hk, Rk = everything.masked(present[..., k, :], k)
        RiH = solve(Rk, Hk, hermitian=True)
        V[k] = mT(RiH)
        if k < K1 - 1:
            if Hn is None:
                Hn = everything.masked(present[..., k + 1, :], k + 1)[0]
            Splus = sym(Smat[k + 1] + mm(mT(Hn), mT(V[k + 1])))
            F, GQG = system.F_at(k + 1), system.GQG_at(k + 1)  # from instant k to k+1
            Bm = eye + mm(Splus, GQG)
            # L = F^T (I + S^+ GQG)^-1, computed as a solve with the transpose.
            L[k] = mT(solve(mT(Bm), bc(F, Bm.shape)))
            Smat[k] = sym(mm(mm(L[k], Splus), F))
            require_finite(Smat[k], "the backward filter's information matrix")
            if steady.reached(Smat[k]):
                Smat[k] = Smat[k + 1]
        Hn = Hk
    A, B, Ps = [], [], []
    for k, st in enumerate(fwd.steps):
        request.step = k
        Sk = Smat[k]
        idx = None if fwd.nodes is None else fwd.nodes[k]  # the forward filter's nodes
        Yf = take_map(fwd_infos[k], idx)
        if k > 0 and st is fwd.steps[k - 1] and Sk is Smat[k - 1]:
            A.append(A[-1])
            B.append(B[-1])
            Ps.append(Ps[-1])
            continue
        if Yf is None:
            Pf = take_map(st.P, idx)
            PS = mm(Pf, Sk)
            Ks = mT(solve(mT(eye + PS), mT(PS)))  # eq. (26)
            Pk = sym(mm(eye - Ks, Pf))  # eq. (27)
            A.append(eye - Ks)  # eq. (28)
            B.append(Pk)
        else:
            # Forward filter still in information form: Millman's formula in information form.
            Pk = inv_or_nan(Yf + Sk)
            A.append(Pk)
            B.append(Pk)
        Ps.append(Pk)
    fwd.smoother = SmootherMaps(L, V, A, B, Ps)
    return fwd
