"""Retrodiction of late measurements in the EKF lanes: Bar-Shalom's Al1, every run at once.

The linear filter's form is `core.retrodict` (its docstring has the equations): the filter
keeps its estimate at the instant tau of its newest measurement (its last update) and the
estimates it had at the instants of the latency window. At each output instant it takes what
has arrived in measurement-time order: a reading not older than tau is an ordinary EKF
prediction to its instant and update; an older one, taken at d < tau, is fused by Al1
(Bar-Shalom, Chen, Mallick 2004; for a lag of one update Bar-Shalom 2002's Algorithm A) with
the updates since the newest stored estimate at a <= d as one equivalent measurement of x_tau:

    S*^-1 = P(tau|a)^-1 (P(tau|a) - P(tau|tau)) P(tau|a)^-1,
    S*^-1 nu* = P(tau|a)^-1 (x(tau|tau) - x(tau|a)),

x(tau|a), P(tau|a) the EKF's prediction of the stored estimate from a to tau. The EKF form
(Bar-Shalom 2002, sec. V):

* the retrodicted state x(d|tau) = f^-1(x(tau|tau) - Q(tau,d) S*^-1 nu*) through the motion's
  inverse from tau back to d (F^-1 for linear motion; f(., -dt) for a nonlinear kind, the flow
  of its ODE run backwards), Q(tau,d) the process noise accumulated along the forward path of
  f^-1(x(tau|tau)) (the only point known before x(d|tau));
* the Jacobians at the retrodicted state: F(tau,d) the product of the motion's Jacobians along
  the forward path of x(d|tau), Q(tau,d) accumulated along it, F(d,tau) = F(tau,d)^-1, H(d) the
  sensors' Jacobian and h at x(d|tau); then P_xv, P_vv, P(d|tau), P_xz, S(d) and the update of
  `core.retrodict`, the residual z(d) - h(x(d|tau)) the sensor's own (bearings wrapped).

The estimate at an output instant is the filter predicted there from tau. The UKF has no
retrodiction here (`core.late_policy.nonlinear_refusal` says why).

Where more than one filter fuses a late sensor (`core.retrodict_fused` for the linear plans):

* *track to track*: each local EKF applies Al1 to its own sensor's late readings, as the one
  filter does (its own tau, its own stored estimates), and the rule fuses the locals' estimates
  at every output instant with their reported covariances, as on time; a rule that reads the
  locals' joint error covariance is refused (`core.late_policy.ekf_retrodict_refusal`). The linear
  plans' J (`core.retrodict_fused`: E cov([x_k; s_k]) E^T) does not carry over: the truth's
  covariance cancels in it only because every local predicts with the F that moves x_k, which
  EKF locals linearised at their own estimates do not. What J needs here is the on-time lanes'
  error form (J_ij <- F_i J_ij F_j^T + Q, each local's own Jacobians) extended to Al1: the
  errors of each local's current and stored estimates and the process noises w_s of the
  window as one vector, its covariance carried through each in-sequence update and each Al1
  (x_d - x(d|tau) = F(d,tau) [x_tau - x(tau|tau) - w(d,tau) + Q(tau,d) S*^-1 nu*-error], the
  errors of x(tau|tau) and the stored x(tau|a) both in that vector). Not built.
* *HKF*: each local restarts from the fused prediction and hands the centre its equivalent
  measurement H_j^T R_j^-1 (z_j - h_j(x) + H_j x), information H_j^T R_j^-1 H_j, H_j the
  Jacobian at the point it restarted from; a late pair is retrodicted by the centre with Al1 in
  information form, the locals' Jacobians taken at the centre's retrodicted state x(d|tau) (the
  state every local restarts from at d). As H^T (H P H^T + R)^-1 = (I + H^T R^-1 H P)^-1 H^T
  R^-1, that is Al1 of one EKF on every sensor with R block-diagonal (the noise HKF believes,
  eqs. 36-37), and in order the centre's update is that filter's stacked update: HKF
  retrodicts as that one filter (equal to rounding).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ...errors import FusionlogError
from ..late_policy import nonlinear_refusal
from ..linalg import mm, mT, solve, sym
from .local import select, stacked, transition


def retrodict_steps(m, feed) -> Iterator:
    """The retrodicting EKFs of machine `m` at each output instant (module docstring):
    `m.retrodicting()` gives each of its filters' sensors and in-order update (None: the
    stacked EKF update), `m.combine` makes the architecture's estimate of theirs; `feed`
    (`late_feed.Feed`) the readings of the last W + 1 instants and the instant each arrives
    (K+1: never), W the largest lag."""
    st = m.st
    if (why := nonlinear_refusal(st.system)) is not None:
        raise FusionlogError(f"{why[0]}: {why[1]}")
    filters = [filter_steps(st, which, feed, up) for which, up in m.retrodicting()]
    for ests in zip(*filters, strict=True):
        yield m.combine(ests)


def filter_steps(st, which: list[int], feed, up=None) -> Iterator:
    """One retrodicting EKF on the sensors `which` at each output instant (x, P), its readings
    from `feed`; `up(i, x, P, zi)` -> (x, P) its update with the readings zi of instant i in
    order (None: the stacked EKF update; HKF's centre gives its own, the same to rounding, so
    that its numbers on time stay its own)."""
    M, K1, W = feed.M, feed.K1, feed.W
    col_sensor = np.concatenate([np.full(len(c), j) for j, c in enumerate(st.cols)])
    mine = np.isin(col_sensor, which)  # other sensors' readings: never used
    x, P = st.start()
    tau = np.zeros(M, dtype=np.intp)
    stored = {0: (x, P)}  # the estimate each run had at instant t (`has`: it has one)
    has = {0: np.ones(M, bool)}
    for k in range(K1):
        for i in range(max(0, k - W), k + 1):
            now = mine & (feed.arrive_at(i, i + 1)[:, 0, col_sensor] == k)
            zi = np.where(now, feed.z_at(i), np.nan)
            here = ~np.isnan(zi).all(-1)
            inseq, late = here & (i >= tau), here & (i < tau)
            if inseq.any():  # predict to i, update
                xp, Pp = advance(st, x, P, tau, np.full(M, i), inseq)
                zs = np.where(inseq[:, None], zi, np.nan)
                if up is None:
                    u = st.update(i, which, xp, Pp, zs)
                    xu, Pu = u.x, u.P
                else:
                    xu, Pu = up(i, xp, Pp, zs)
                x, P = select(inseq, (xu, Pu), (x, P))
                tau = np.where(inseq, i, tau)
            if late.any():
                x, P = select(late, al1(st, which, x, P, tau, i, zi, stored, has), (x, P))
            done = inseq | late
            if done.any():  # the estimate at tau, stored at tau
                for t in np.unique(tau[done]):
                    w = done & (tau == t)
                    old = stored.get(t, (x, P))
                    stored[t] = select(w, (x, P), old)
                    has[t] = has.get(t, np.zeros(M, bool)) | w
        keep_window(st, stored, has, k + 1 - W)
        yield advance(st, x, P, tau, np.full(M, k), np.ones(M, bool))


def advance(st, x, P, frm: np.ndarray, to: np.ndarray, runs: np.ndarray):
    """The EKF's prediction of (x, P) from instant frm to instant to >= frm, per run (M,), in
    the runs `runs` (the others unchanged): one instant at a time, as the filter predicts."""
    go = runs & (to > frm)
    if not go.any():
        return x, P
    for t in range(int(frm[go].min()) + 1, int(to[go].max()) + 1):
        on = go & (frm < t) & (t <= to)
        if on.any():
            xp, Pp, _, _ = st.predict(t, x, P)
            x, P = select(on, (xp, Pp), (x, P))
    return x, P


def flow(st, x: np.ndarray, d: int, tau: np.ndarray, runs: np.ndarray):
    """(F(tau,d), Q(tau,d)) along the motion's forward path of x from instant d to tau, per
    run: the products of its Jacobians and the process noise accumulated through them."""
    M, n = x.shape
    F = np.broadcast_to(np.eye(n), (M, n, n)).copy()
    Q = np.zeros((M, n, n))
    for t in range(d + 1, int(tau[runs].max()) + 1):
        on = (runs & (t <= tau))[:, None, None]
        motion, dt = transition(st.system, t)
        Ft = np.broadcast_to(motion.jacobian(x, dt), (M, n, n))
        F = np.where(on, mm(Ft, F), F)
        Q = np.where(on, sym(mm(mm(Ft, Q), mT(Ft)) + motion.Q(dt)), Q)
        x = np.where(on[:, :, 0], motion.f(x, dt), x)
    return F, Q


def backward(st, x: np.ndarray, d: int, tau: np.ndarray, runs: np.ndarray) -> np.ndarray:
    """The motion's inverse from instant tau back to d, per run: F^-1 for linear motion, the
    flow run backwards (f(., -dt)) for a nonlinear kind."""
    for t in range(int(tau[runs].max()), d, -1):
        on = (runs & (t <= tau))[:, None]
        motion, dt = transition(st.system, t)
        if motion.linear:
            prev = np.linalg.solve(motion.F(dt), x.T).T
        else:
            prev = motion.f(x, -dt)
        x = np.where(on, prev, x)
    return x


def al1(st, which, x, P, tau, d: int, zd, stored: dict, has: dict):
    """Al1 (module docstring) for the runs whose reading zd (M, m) of instant d is older
    than their last update tau; (x, P) updated (other runs: anything, the caller selects)."""
    M, n = x.shape
    runs = ~np.isnan(zd).all(-1) & (d < tau)
    # the newest stored estimate at a <= d, per run, predicted to tau
    a = np.full(M, -1)
    xa, Pa = x, P
    for t in sorted(t for t in stored if t <= d):
        w = has[t] & runs
        a = np.where(w, t, a)
        xa, Pa = select(w, stored[t], (xa, Pa))
    xta, Pta = advance(st, xa, Pa, a, tau, runs)
    Pi = solve(Pta, np.broadcast_to(np.eye(n), (M, n, n)), hermitian=True)
    A = sym(mm(mm(Pi, Pta - P), Pi))  # S*^-1
    g = np.einsum("mij,mj->mi", Pi, x - xta)  # S*^-1 nu*
    _, Q0 = flow(st, backward(st, x, d, tau, runs), d, tau, runs)
    xd = backward(st, x - np.einsum("mij,mj->mi", Q0, g), d, tau, runs)
    Fkd, Qkd = flow(st, xd, d, tau, runs)  # the Jacobians at the retrodicted state
    Fdk = np.linalg.inv(Fkd)
    Pxv = Qkd - mm(mm(Pta, A), Qkd)
    Pvv = Qkd - mm(mm(Qkd, A), Qkd)
    Pd = sym(mm(mm(Fdk, P + Pvv - Pxv - mT(Pxv)), mT(Fdk)))
    present = ~np.isnan(zd) & runs[:, None]
    sens = [j for j in which if present[:, st.cols[j]].any()]
    model = stacked(st.system, sens, d)  # R of instant d where it varies
    cols = np.concatenate([st.cols[j] for j in sens])
    zc, pc = zd[:, cols], present[:, cols]
    H = model.jacobian(xd) * pc[:, :, None]
    R = np.where(pc[:, :, None] == pc[:, None, :], model.R, 0.0)
    y = model.residual(np.where(pc, zc, 0.0), model.h(xd)) * pc
    Sd = sym(mm(mm(H, Pd), mT(H)) + R)
    Pxz = mm(mm(P - Pxv, mT(Fdk)), mT(H))
    Wg = mT(solve(Sd, mT(Pxz), hermitian=True, what="the innovation covariance"))
    return x + np.einsum("mij,mj->mi", Wg, y), sym(P - mm(Wg, mT(Pxz)))


def keep_window(st, stored: dict, has: dict, b: int) -> None:
    """The stored estimates a later reading can need (taken at b or later): those from b on,
    and in each run the newest older one moved to b by prediction (no update between: the
    same equivalent measurement), as `core.retrodict` keeps them."""
    older = [t for t in stored if t <= b]
    if b <= 0 or not older:
        return
    M = next(iter(has.values())).shape[0]
    need = ~has.get(b, np.zeros(M, bool))
    if need.any():
        frm = np.full(M, b)
        xb, Pb = stored.get(b, stored[max(older)])
        for t in sorted(older):
            w = has[t] & need
            frm = np.where(w, t, frm)
            xb, Pb = select(w, stored[t], (xb, Pb))
        stored[b] = advance(st, xb, Pb, frm, np.full(M, b), need)
        has[b] = np.ones(M, bool)
    for t in [t for t in stored if t < b]:
        del stored[t], has[t]
