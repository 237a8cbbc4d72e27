"""Retrodiction of late measurements: Bar-Shalom's one-step solution, as a plan.

The filter keeps its estimate at the time of its newest measurement (its last update) and
the estimates it had at the instants of the latency window. At each output instant it takes
what has arrived, in measurement-time order: a reading not older than its last update is an
ordinary prediction and Joseph update; an older one (an out-of-sequence measurement, OOSM,
taken at tau_d < t_k, the last update) is fused by

* Y. Bar-Shalom, "Update with out-of-sequence measurements in tracking: exact solution",
  IEEE TAES 38(3), 2002, Algorithm A (a lag of one update: exact), in the form of
* Y. Bar-Shalom, H. Chen, M. Mallick, "One-step solution for the multistep out-of-sequence-
  measurement problem in tracking", IEEE TAES 40(1), 2004, Al1: the updates since the last
  stored estimate at t_a <= tau_d as one equivalent measurement of x_k (H* = I), whose
  S*^-1 = P(k|a)^-1 (P(k|a) - P(k|k)) P(k|a)^-1 and S*^-1 nu* = P(k|a)^-1 (x(k|k) - x(k|a)):

      x(d|k)  = F(d,k) [x(k|k) - Q(k,d) S*^-1 nu*]
      P_xv    = Q(k,d) - P(k|a) S*^-1 Q(k,d),     P_vv = Q(k,d) - Q(k,d) S*^-1 Q(k,d)
      P(d|k)  = F(d,k) [P(k|k) + P_vv - P_xv - P_xv'] F(d,k)'
      P_xz    = [P(k|k) - P_xv] F(d,k)' H(d)',   S(d) = H(d) P(d|k) H(d)' + R(d)
      x(k|d)  = x(k|k) + P_xz S(d)^-1 [z(d) - H(d) x(d|k)]
      P(k|d)  = P(k|k) - P_xz S(d)^-1 P_xz'

  with a one-update lag this is Algorithm A, exact; over several updates it is an
  approximation (the stored estimates are not corrected by later OOSMs).

The estimate at an output instant is the filter predicted there. The gains depend only on
which readings arrive when, so the filter is an affine map of the readings: the plan's state
is [current estimate; the estimates stored at instants k-W..k; the last W readings], its maps
computed once per arrival pattern (per run where the delays differ), and the exact analysis
takes it as any plan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .architectures import Plan, StepMap
from .linalg import sym
from .model import System

__all__ = ["retrodict_plan"]


@dataclass
class _Layout:
    """The plan's state s_k = [cur (n); stored x at k-q, q = 0..W (n each); z_{k-q}, q =
    0..W-1 (m each)], and step k's inputs u = [s_{k-1}; z_k]."""

    n: int
    m: int
    W: int

    @property
    def d(self) -> int:
        return self.n * (self.W + 2) + self.W * self.m

    def stored(self, q: int) -> slice:
        return slice(self.n * (1 + q), self.n * (2 + q))

    def buffered(self, q: int) -> slice:
        a = self.n * (self.W + 2) + q * self.m
        return slice(a, a + self.m)


class _Transitions:
    """F and Q (process noise in state space) from instant a to instant b >= a."""

    def __init__(self, system: System):
        self.system, self.cache = system, {}

    def __call__(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        got = self.cache.get((a, b))
        if got is None:
            n = self.system.n
            F, Q = np.eye(n), np.zeros((n, n))
            for t in range(a + 1, b + 1):
                Ft = self.system.F_at(t)
                F, Q = Ft @ F, Ft @ Q @ Ft.T + self.system.GQG_at(t)
            got = self.cache[a, b] = (F, sym(Q))
        return got


def _one_run(
    system: System,
    present: np.ndarray,
    arrive: np.ndarray,
    sensors: list[int],
    W: int,
    trans: _Transitions,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(T, U, O, P) of every step for one arrival pattern: `present` (K+1, m), `arrive`
    (K+1, S) the instant each reading arrives by, the filter on `sensors`."""
    n, m = system.n, system.m
    lay = _Layout(n, m, W)
    d = lay.d
    H_all = system.linear_measurement()
    slices = system.sensor_slices
    prior = system.prior
    assert prior is not None
    K1 = present.shape[0]
    P = prior.cov.copy()
    tau = 0  # the time (instant) of the filter's estimate
    Pst = {0: P}  # the covariances of the stored estimates, by instant
    out = []
    for k in range(K1):
        # expressions: rows over u = [s_{k-1}; z_k]
        cur = np.zeros((n, d + m))
        cur[:, :n] = np.eye(n)
        stored = {}
        for t in Pst:
            q = k - 1 - t
            e = np.zeros((n, d + m))
            if q < 0:  # k = 0: the prior, the current estimate
                e[:, :n] = np.eye(n)
            else:
                e[:, lay.stored(q)] = np.eye(n)
            stored[t] = e

        def reading(i: int, comps: np.ndarray, k: int = k) -> np.ndarray:
            """The rows of u that are the components `comps` of z_i."""
            e = np.zeros((len(comps), d + m))
            if i == k:
                e[np.arange(len(comps)), d + comps] = 1.0
            else:
                e[np.arange(len(comps)), lay.buffered(k - 1 - i).start + comps] = 1.0
            return e

        groups: dict[int, list[int]] = {}
        for i in range(max(0, k - W), k + 1):
            for j in sensors:
                if arrive[i, j] == k and present[i, slices[j]].any():
                    groups.setdefault(i, []).append(j)
        for i in sorted(groups):
            comps = np.concatenate(
                [np.arange(m)[slices[j]][present[i, slices[j]]] for j in groups[i]]
            )
            H, R, z = H_all[comps], system.R_at(i)[np.ix_(comps, comps)], reading(i, comps)
            if i >= tau:  # in sequence: predict to i, Joseph update
                F, Q = trans(tau, i)
                cur, P, tau = F @ cur, sym(F @ P @ F.T) + Q, i
                S = H @ P @ H.T + R
                K = np.linalg.solve(S, H @ P).T
                IKH = np.eye(n) - K @ H
                cur = IKH @ cur + K @ z
                P = sym(IKH @ P @ IKH.T + K @ R @ K.T)
            else:  # out of sequence: Al1 (Algorithm A for a one-update lag)
                a = max(t for t in Pst if t <= i)
                Fa, Qa = trans(a, tau)
                Pp = sym(Fa @ Pst[a] @ Fa.T) + Qa
                Fkd, Qkd = trans(i, tau)
                Fdk = np.linalg.inv(Fkd)
                Ppi = np.linalg.inv(Pp)
                A = sym(Ppi @ (Pp - P) @ Ppi)  # S*^-1
                g = Ppi @ (cur - Fa @ stored[a])  # S*^-1 nu*
                xd = Fdk @ (cur - Qkd @ g)
                Pxv = Qkd - Pp @ A @ Qkd
                Pvv = Qkd - Qkd @ A @ Qkd
                Pd = sym(Fdk @ (P + Pvv - Pxv - Pxv.T) @ Fdk.T)
                Sd = H @ Pd @ H.T + R
                Pxz = (P - Pxv) @ Fdk.T @ H.T
                Wg = np.linalg.solve(Sd, Pxz.T).T
                cur = cur + Wg @ (z - H @ xd)
                P = sym(P - Wg @ Pxz.T)
            Pst[tau], stored[tau] = P, cur
        Pst = _keep_window(Pst, stored, k + 1 - W, trans)
        # the new state: cur, the stored estimates of k-q, the readings z_k..z_{k-W+1}
        rows = np.zeros((d, d + m))
        rows[:n] = cur
        for q in range(W + 1):
            if k - q in stored:
                rows[lay.stored(q)] = stored[k - q]
        if W:
            rows[lay.buffered(0), d:] = np.eye(m)
            for q in range(1, W):
                rows[lay.buffered(q), lay.buffered(q - 1)] = np.eye(m)
        Fo, Qo = trans(tau, k)
        O = np.zeros((n, d))
        O[:, :n] = Fo
        out.append((rows[:, :d], rows[:, d:], O, sym(Fo @ P @ Fo.T) + Qo))
    return out


def _keep_window(Pst: dict, stored: dict, b: int, trans: _Transitions) -> dict:
    """The stored estimates a later OOSM can need (taken at b or later): those from b on, and
    the newest older one moved to b by prediction (no update between: the same equivalent
    measurement), so that every one sits in the plan's window."""
    older = [t for t in Pst if t <= b]
    if b < 0 or not older:
        return Pst
    tb = max(older)
    if tb < b:
        F, Q = trans(tb, b)
        stored[b], Pst[b] = F @ stored[tb], sym(F @ Pst[tb] @ F.T) + Q
    return {t: v for t, v in Pst.items() if t >= b}


def retrodict_plan(
    system: System,
    name: str,
    present: np.ndarray,
    arrive: np.ndarray,
    sensors: list[int],
    W: int,
) -> Plan:
    """The retrodicting filter on `sensors` as a plan: `present` (K+1, m) or (M, K+1, m),
    `arrive` (K+1, S) or (M, K+1, S) the instant each reading arrives by; maps shared by all
    runs, or per run (computed once per distinct pattern)."""
    n = system.n
    lay = _Layout(n, system.m, W)
    trans = _Transitions(system)
    assert system.prior is not None
    s0 = np.zeros(lay.d)
    s0[:n] = system.prior.mean
    s0[lay.stored(0)] = system.prior.mean  # unused: instant 0's stored estimate is cur's
    if present.ndim == 2 and arrive.ndim == 2:
        maps = _one_run(system, present, arrive, sensors, W, trans)
        steps = [StepMap(T, U, O, P, np.zeros((lay.d, n))) for T, U, O, P in maps]
        per_run = False
    else:
        M = np.broadcast_shapes(present.shape[:-2], arrive.shape[:-2])[0]
        pres = np.broadcast_to(present, (M,) + present.shape[-2:])
        arr = np.broadcast_to(arrive, (M,) + arrive.shape[-2:])
        key = np.concatenate([pres.reshape(M, -1), arr.reshape(M, -1)], axis=1)
        uniq, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        runs = [_one_run(system, pres[r], arr[r], sensors, W, trans) for r in first]
        inverse = inverse.ravel()
        steps = []
        for k in range(pres.shape[1]):
            T, U, O, P = (np.stack([r[k][f] for r in runs])[inverse] for f in range(4))
            steps.append(StepMap(T, U, O, P, np.zeros((M, lay.d, n))))
        per_run = True
    return Plan(name, s0, steps, per_run=per_run, D0=np.zeros((lay.d, n)), complete=False)
