"""Retrodiction where the late sensor is fused by more than one filter: the hierarchical filter's
centre and the track-to-track locals (DESIGN.md "Late measurements"; Al1 itself: `retrodict`).

*HKF.* Each local filter of the hierarchical KF restarts from the fused prediction and hands
the centre its equivalent measurement P_j^-1 x_j - P^-1 x = H_j^T R_j^-1 z_j, information
H_j^T R_j^-1 H_j (eqs. 36-37): whatever prediction it restarted from, it is sensor j's
reading in information form. A late reading reaches the centre as that pair, stamped with its
time, and the centre retrodicts it with Al1 in information form: with C = cov(x_k, x_d) and
P(d|k) as in Al1, x(k|d) = x(k|k) + C (I + I_d P(d|k))^-1 (i_d - I_d x(d|k)), I_d, i_d the
sum over the sensors of instant d. Since H^T (H P H^T + R)^-1 = (I + H^T R^-1 H P)^-1 H^T R^-1,
that is Al1 on the readings with the noise HKF believes, block-diagonal R (its on-time form is
the CKF on that R as well): the plan is the retrodicting filter on every sensor with R's
cross-sensor blocks removed.

*Track to track.* Each local filter applies Al1 to its own sensor's late readings
(`retrodict_maps` on that sensor); the registered rule (`track_to_track.build_rule`'s
`definition.Rule`) fuses the locals' estimates of x_k at every output instant, with their
reported covariances. A rule that reads the locals' joint error covariance J (MSC-GMF, AVG)
gets it from the plans' affine maps: y_k = [x_k; s_k] (s the locals' states) follows

    y_k = A_k y_{k-1} + B_k w_k + [0; U_k] v_k,   A = [[F, 0], [U H F, T]],  B = [I; U H],

so cov(y_k) = A cov(y_{k-1}) A^T + B Q B^T + [0; U] R [0; U]^T (R with its cross-sensor
blocks: eq. 35's K_i R_ij K_j^T), and J = E cov(y) E^T for the errors e_j = x_k - O_j s_j.
Over several updates Al1 is an approximation, so J's diagonal blocks are the locals' true error
covariances, not the ones they report. The locals keep one copy of the last W readings.
"""

from __future__ import annotations

import numpy as np

from .architectures import Plan, StepMap, definition
from .architectures.hkf import independent_noise
from .linalg import mT, sym
from .model import System
from .retrodict import retrodict_maps, retrodict_plan

__all__ = ["late_retrodict_plan"]


def late_retrodict_plan(
    system: System,
    arch: str,
    base: str,
    present: np.ndarray,
    arrive: np.ndarray,
    filters: list[list[int]],
    lags: list[np.ndarray],
    criterion: str = "trace",
) -> Plan:
    """Architecture `arch` (registered as `base`) retrodicting its late readings: one filter on
    `filters[0]` (CKF, SKF), the hierarchical centre, or one local per sensor and the rule.
    `lags[j]`: the lags sensor j's readings arrive with; each filter keeps the window of its
    own sensors' largest lag."""
    locals_kind = definition(base).locals
    if locals_kind == "per-sensor":
        return _fused(system, arch, base, present, arrive, lags, criterion)
    W = max(int(lags[j].max()) for j in filters[0])
    if locals_kind == "hierarchical":
        return retrodict_plan(independent_noise(system), arch, present, arrive, filters[0], W)
    return retrodict_plan(system, arch, present, arrive, filters[0], W)


def _fused(
    system: System,
    arch: str,
    base: str,
    present: np.ndarray,
    arrive: np.ndarray,
    lags: list[np.ndarray],
    criterion: str,
) -> Plan:
    """The locals (one retrodicting filter per sensor, local j keeping the window W_j of its
    sensor's largest lag) and the rule as one plan: state [the locals' estimates and stored
    estimates; the last W = max W_j readings, shared]."""
    n, m = system.n, system.m
    S = len(system.sensors)
    Ws = [int(lj.max()) for lj in lags]
    W = max(Ws)
    nbs = [n * (Wj + 2) for Wj in Ws]
    at = np.concatenate([[0], np.cumsum(nbs)])  # local j's rows: at[j]:at[j+1]
    B = W * m
    dC = int(at[-1]) + B
    locs = [retrodict_maps(system, present, arrive, [j], Ws[j]) for j in range(S)]
    per_run = any(pr for _, pr in locs)
    if per_run:  # every local's maps per run
        M = max(mk[0][0].shape[0] for mk, pr in locs if pr)
        locs = [
            (mk if pr else [tuple(np.broadcast_to(f, (M,) + f.shape) for f in st) for st in mk], pr)
            for mk, pr in locs
        ]
    else:
        locs = [(mk, False) for mk, _ in locs]
    arch_def = definition(base)
    H, K1 = system.linear_measurement(), len(locs[0][0])
    prior = system.prior
    assert prior is not None
    steps, omegas = [], []
    cov = None  # cov([x_k; s_k]) when the rule reads J
    for k in range(K1):
        maps = [mk[k] for mk, _ in locs]
        batch = maps[0][0].shape[:-2]
        T = np.zeros(batch + (dC, dC))
        U = np.zeros(batch + (dC, m))
        Ol = np.zeros(batch + (S * n, dC))
        for j, (Tj, Uj, Oj, _) in enumerate(maps):
            nb, rows, buf = nbs[j], slice(at[j], at[j + 1]), at[-1]
            T[..., rows, rows] = Tj[..., :nb, :nb]
            T[..., rows, buf : buf + Ws[j] * m] = Tj[..., :nb, nb:]  # its newest W_j readings
            U[..., rows, :] = Uj[..., :nb, :]
            Ol[..., j * n : (j + 1) * n, rows] = Oj[..., :, :nb]
        wide = Ws.index(W)  # a local that keeps all W readings: their shift
        nw, buf = nbs[wide], at[-1]
        T[..., buf:, buf:] = maps[wide][0][..., nw:, nw:]
        U[..., buf:, :] = maps[wide][1][..., nw:, :]
        Ploc = np.stack([mp[3] for mp in maps], axis=-3)  # batch + (S, n, n)
        J = None
        if arch_def.joint:
            cov = _moments(system, k, T, U, H, cov, prior.cov)
            E = np.zeros(batch + (S * n, n + dC))  # e_j = x_k - O_j s_j
            E[..., :n] = np.tile(np.eye(n), (S, 1))
            E[..., n:] = -Ol
            J = sym(E @ cov @ mT(E))
        C, Pf, w = _rule(arch_def, Ploc, J, criterion)
        omegas.append(w)
        steps.append(StepMap(T, U, C @ Ol, Pf, np.zeros(batch + (dC, n))))
    s0 = np.zeros(dC)
    for j in range(S):
        s0[at[j] : at[j] + n] = prior.mean
    omega = None
    if any(w is not None for w in omegas):
        omega = np.stack([np.broadcast_to(w, batch + (S,)) for w in omegas], axis=-2)
    plan = Plan(arch, s0, steps, per_run=per_run, D0=np.zeros((dC, n)), complete=False)
    # plan.system stays None: with D = 0 the state s is not D x plus an error, so the exact
    # analysis keeps the true state's terms (`moments.coupling`)
    plan.omega = omega
    return plan


def _rule(arch_def, P: np.ndarray, J: np.ndarray | None, criterion: str):
    """(C, P_fused, omega or None) of the registered rule on the locals, with a batch axis
    always (the rules' kernels work on batches of problems)."""
    one = P.ndim == 3
    if one:
        P, J = P[None], None if J is None else J[None]
    found: dict[str, np.ndarray] = {}
    if arch_def.information:
        C, Pf = arch_def.rule(P, J, criterion, found=found)
    else:
        C, Pf = arch_def.rule(P, J, criterion)
    w = found.get("omega")
    C = np.broadcast_to(C, Pf.shape[:-2] + C.shape[-2:])
    if one:
        C, Pf, w = C[0], Pf[0], None if w is None else w[0]
    return C, Pf, w


def _moments(system, k, T, U, H, cov, P0):
    """cov([x_k; s_k]) from cov([x_{k-1}; s_{k-1}]) (module docstring); at k = 0 from [x_0; s_0]
    (s_0 known), through step 0's maps without a prediction."""
    n = system.n
    batch = T.shape[:-2]
    dy = n + T.shape[-1]
    if cov is None:
        cov = np.zeros(batch + (dy, dy))
        cov[..., :n, :n] = P0
    F = np.eye(n) if k == 0 else system.F_at(k)
    Q = np.zeros((n, n)) if k == 0 else system.GQG_at(k)
    UH = U @ H
    A = np.zeros(batch + (dy, dy))
    A[..., :n, :n] = F
    A[..., n:, :n] = UH @ F
    A[..., n:, n:] = T
    Bw = np.concatenate([np.broadcast_to(np.eye(n), UH.shape[:-2] + (n, n)), UH], axis=-2)
    out = A @ cov @ mT(A) + Bw @ Q @ mT(Bw)
    out[..., n:, n:] += U @ system.R_at(k) @ mT(U)
    return sym(out)
