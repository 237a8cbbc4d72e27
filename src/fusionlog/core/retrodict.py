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
is [current estimate; the estimates stored at instants k-W..k; the last W readings], and the
exact analysis takes it as any plan. Per run (random delays, dropouts) the recursion runs on
all distinct arrival patterns at once, as a batch: each run's readings of one instant enter
through the full H with the absent rows zeroed and R's absent rows and columns replaced by the
identity, which gives them zero gain (S is block diagonal after the permutation to present /
absent), so one batched solve serves every pattern; the branch (in sequence or Al1) and the
transitions are taken per run. The recursion of the gains (`Recursion`) keeps a bounded state
-- each pattern's P, the instant of its last update and the stored estimates' covariances over
the window -- so it is resumable: the whole run is one call, a long log one call per block of
time (`core.retrodict_blocks`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .architectures import Plan, StepMap
from .linalg import mT, sym
from .model import System

__all__ = [
    "Recursion",
    "Transitions",
    "initial_error_form",
    "initial_state",
    "retrodict_maps",
    "retrodict_plan",
]


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


class Transitions:
    """F and Q (process noise in state space) from instant a to instant b >= a, kept by the
    pair -- by b - a alone where F and Q are the same over every interval (the same product,
    whatever a: the same bits), so a long log's cache stays as small as its window."""

    def __init__(self, system: System):
        self.system, self.cache, self.inverses = system, {}, {}
        self.invariant = system.Fs is None and system.Qs is None

    def key(self, a: int, b: int) -> tuple[int, int]:
        """The cache's key of the pair (a, b)."""
        return (0, b - a) if self.invariant else (a, b)

    def __call__(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        a, b = int(a), int(b)
        key = self.key(a, b)
        got = self.cache.get(key)
        if got is None:
            n = self.system.n
            F, Q = np.eye(n), np.zeros((n, n))
            for t in range(a + 1, b + 1):
                Ft = self.system.F_at(t)
                F, Q = Ft @ F, Ft @ Q @ Ft.T + self.system.GQG_at(t)
            got = self.cache[key] = (F, sym(Q))
        return got

    def back(self, a: int, b: int) -> tuple[np.ndarray]:
        """(F(a, b)^-1,): x_a = F(a, b)^-1 x_b without noise; zero when F(a, b) is singular or
        ill-conditioned (cond > 1e8, its inverse would amplify rounding): that block of the
        error form D is then 0, as before (`error_form`)."""
        a, b = int(a), int(b)
        key = self.key(a, b)
        got = self.inverses.get(key)
        if got is None:
            F = self(a, b)[0]
            usable = np.isfinite(F).all() and np.linalg.cond(F) <= 1e8
            got = self.inverses[key] = (np.linalg.inv(F) if usable else np.zeros_like(F),)
        return got

    def gathered(self, a: np.ndarray, b: np.ndarray | int, of=None) -> tuple[np.ndarray, ...]:
        """F, Q (or what `of`, default self, gives) from a[r] to b[r] for every run r, (R, n, n)
        each (one lookup per distinct pair)."""
        of = self if of is None else of
        if a.size == 1:  # one run: a view (broadcast_to costs more than the products here)
            return tuple(X[None] for X in of(a.flat[0], np.asarray(b).flat[0]))
        b = np.broadcast_to(b, a.shape)
        if (a == a.flat[0]).all() and (b == b.flat[0]).all():  # one pair (e.g. one pattern)
            return tuple(np.broadcast_to(X, a.shape + X.shape) for X in of(a.flat[0], b.flat[0]))
        wide = int(max(a.max(initial=0), b.max(initial=0))) + 1
        keys, inv = np.unique(a * wide + b, return_inverse=True)  # the pairs as numbers
        got = [of(p, q) for p, q in zip(keys // wide, keys % wide, strict=True)]
        inv = inv.ravel()
        return tuple(np.stack(X)[inv] for X in zip(*got, strict=True))


def _masked(H: np.ndarray, R: np.ndarray, cm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H (m, n) and R (m, m) of the components `cm` (R', m) of each run: absent rows of H zero,
    absent rows and columns of R the identity's (zero gain for them, see the module's
    docstring)."""
    Hm = H * cm[:, :, None]
    Rm = R * (cm[:, :, None] & cm[:, None, :])
    ar = np.arange(R.shape[0])
    Rm[:, ar, ar] += ~cm
    return Hm, Rm


def _update(cur, P, Hm, Rm, z):
    """Joseph update of the expressions `cur` (R', n, D) with covariance P with the readings z
    (m, D)."""
    n = P.shape[-1]
    S = Hm @ P @ mT(Hm) + Rm
    K = mT(np.linalg.solve(S, Hm @ P))
    IKH = np.eye(n) - K @ Hm
    return IKH @ cur + K @ z, sym(IKH @ P @ mT(IKH) + K @ Rm @ mT(K))


def _al1(cur, P, Hm, Rm, z, xa, Pa, Fa, Qa, Fkd, Qkd):
    """Al1 (module docstring) for a batch: the stored estimate xa (expressions), Pa at t_a, F, Q
    from t_a and from the OOSM's time t_d to the last update t_k."""
    Pp = sym(Fa @ Pa @ mT(Fa)) + Qa
    Fdk = np.linalg.inv(Fkd)
    Ppi = np.linalg.inv(Pp)
    A = sym(Ppi @ (Pp - P) @ Ppi)  # S*^-1
    g = Ppi @ (cur - Fa @ xa)  # S*^-1 nu*
    xd = Fdk @ (cur - Qkd @ g)
    Pxv = Qkd - Pp @ A @ Qkd
    Pvv = Qkd - Qkd @ A @ Qkd
    Pd = sym(Fdk @ (P + Pvv - Pxv - mT(Pxv)) @ mT(Fdk))
    Sd = Hm @ Pd @ mT(Hm) + Rm
    Pxz = (P - Pxv) @ mT(Fdk) @ mT(Hm)
    Wg = mT(np.linalg.solve(Sd, mT(Pxz)))
    return cur + Wg @ (z - Hm @ xd), sym(P - Wg @ mT(Pxz))


def _last_valid(valid: np.ndarray) -> np.ndarray:
    """Index of the last True of each row (R', L) (each row has one)."""
    return valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)


class Recursion:
    """The retrodicting filter's gain recursion on `sensors` (window W) for M arrival patterns,
    resumable: `steps` gives the (T, U, O, P, D) of instants k0..k1-1 and keeps what the next
    instant needs -- each pattern's covariance P, the instant tau of its estimate and the
    covariances of the estimates stored over the window (`sP`, `sval`) -- so the log can be
    taken whole (`_batch`) or block by block (`core.retrodict_blocks`). During step k the
    stored estimates are kept by instant t = k-1-W+r, r = 0..W+1 (`sval`: stored for that run;
    their expressions `sx` rows over u = [s_{k-1}; z_k])."""

    def __init__(self, system: System, sensors: list[int], W: int, M: int, trans: Transitions):
        n = system.n
        self.system, self.sensors, self.W, self.trans = system, sensors, W, trans
        self.lay = _Layout(n, system.m, W)
        self.H = system.linear_measurement()
        assert system.prior is not None
        L = W + 2
        self.P = np.broadcast_to(system.prior.cov, (M, n, n)).copy()
        self.tau = np.zeros(M, dtype=np.intp)  # the instant of each run's estimate
        self.sP = np.zeros((M, L, n, n))
        self.sval = np.zeros((M, L), dtype=bool)
        self.next_instant = 0

    def steps(
        self, present: np.ndarray, arrive: np.ndarray, k0: int, k1: int, first: int = 0
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """(T, U, O, P, D), each (M, ...), of the steps k0..k1-1: `present` (M, rows, m) and
        `arrive` (M, rows, S) (the instant each reading arrives by) of the instants first..,
        from max(0, k0 - W) on at least."""
        if k0 != self.next_instant or first > max(0, k0 - self.W):
            raise ValueError(f"retrodiction's steps in order: {k0} after {self.next_instant}")
        system, sensors, W, trans, lay = self.system, self.sensors, self.W, self.trans, self.lay
        n, m = system.n, system.m
        d = lay.d
        D = d + m
        H, slices = self.H, system.sensor_slices
        prior = system.prior
        P, tau, sP, sval = self.P, self.tau, self.sP, self.sval
        M = P.shape[0]
        L = W + 2
        eye, eye_m = np.eye(n), np.eye(m)
        R0 = system.R if system.Rs is None else None  # the property builds it on every call
        # each component's arrival instant, and whether the filter takes it (its sensors')
        comp = np.zeros(m, dtype=np.intp)
        fused = np.zeros(m, dtype=bool)
        for j in sensors:
            comp[slices[j]], fused[slices[j]] = j, True
        took = present & fused
        when = arrive[..., comp]
        out = []
        for k in range(k0, k1):
            base = k - 1 - W
            cur = np.zeros((M, n, D))
            cur[:, :, :n] = eye
            sx = np.zeros((M, L, n, D))
            for r in range(W + 1):
                sx[:, r, :, lay.stored(W - r)] = eye
            if k == 0:  # the prior: instant 0's stored estimate is the current one
                sx[:, W + 1, :, :n] = eye
                sP[:, W + 1], sval[:, W + 1] = prior.cov, True
            lo = max(0, k - W)
            # the components of instants lo..k that arrive at k, (M, k+1-lo, m), at once
            hits = took[:, lo - first : k + 1 - first] & (when[:, lo - first : k + 1 - first] == k)
            for i in (np.flatnonzero(hits.any(axis=(0, 2))) + lo).tolist():
                cm = hits[:, i - lo]
                g = cm.any(axis=1)
                z = np.zeros((m, D))  # the rows of u that are z_i
                c0 = d if i == k else lay.buffered(k - 1 - i).start
                z[:, c0 : c0 + m] = eye_m
                Hm, Rm = _masked(H, system.R_at(i) if R0 is None else R0, cm)
                ins = np.flatnonzero(g & (i >= tau))  # in sequence: predict to i, Joseph update
                if len(ins):
                    F, Q = trans.gathered(tau[ins], i)
                    c, Pp = F @ cur[ins], sym(F @ P[ins] @ mT(F)) + Q
                    cur[ins], P[ins] = _update(c, Pp, Hm[ins], Rm[ins], z)
                    tau[ins] = i
                oos = np.flatnonzero(g & (i < tau))  # out of sequence: Al1
                if len(oos):
                    a = _last_valid(sval[oos] & (np.arange(L) <= i - base))
                    t_a, t_k = a + base, tau[oos]
                    Fa, Qa = trans.gathered(t_a, t_k)
                    Fkd, Qkd = trans.gathered(np.full(len(oos), i), t_k)
                    cur[oos], P[oos] = _al1(
                        cur[oos], P[oos], Hm[oos], Rm[oos], z,
                        sx[oos, a], sP[oos, a], Fa, Qa, Fkd, Qkd,
                    )  # fmt: skip
                got = np.flatnonzero(g)
                r = tau[got] - base
                sx[got, r], sP[got, r], sval[got, r] = cur[got], P[got], True
            _keep_window(sx, sP, sval, k + 1 - W, base, trans)
            # the new state: cur, the stored estimates of k-q, the readings z_k..z_{k-W+1}
            rows = np.zeros((M, d, D))
            rows[:, :n] = cur
            for q in range(W + 1):
                r = W + 1 - q  # instant k - q
                rows[:, lay.stored(q)] = sx[:, r] * sval[:, r, None, None]
            if W:
                rows[:, lay.buffered(0), d:] = eye_m
                for q in range(1, W):
                    rows[:, lay.buffered(q), lay.buffered(q - 1)] = eye_m
            Fo, Qo = trans.gathered(tau, k)
            O = np.zeros((M, n, d))
            O[:, :, :n] = Fo
            T, U = np.ascontiguousarray(rows[:, :, :d]), np.ascontiguousarray(rows[:, :, d:])
            Pk = sym(Fo @ P @ mT(Fo)) + Qo
            out.append((T, U, O, Pk, _error_form(lay, H, k, tau, sval, trans)))
            sP[:, :-1], sval[:, :-1] = sP[:, 1:], sval[:, 1:]  # to step k+1's instants
            sval[:, -1] = False
        self.next_instant = k1
        return out


def _batch(
    system: System,
    present: np.ndarray,
    arrive: np.ndarray,
    sensors: list[int],
    W: int,
    trans: Transitions,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(T, U, O, P, D), each (M, ...), of every step for M arrival patterns at once: `present`
    (M, K+1, m), `arrive` (M, K+1, S) the instant each reading arrives by, the filter on
    `sensors` (`Recursion` over the whole horizon)."""
    M, K1 = present.shape[:2]
    return Recursion(system, sensors, W, M, trans).steps(present, arrive, 0, K1)


def _error_form(lay: _Layout, H, k: int, tau, sval, trans: Transitions) -> np.ndarray:
    """D_k (M, d, n), s_k = D_k x_k without noise (`StepMap.D`): the current estimate is
    x_tau = F(tau, k)^-1 x_k (every update, in sequence or Al1, is unbiased), a stored one at
    instant k-q is x_{k-q} = F(k-q, k)^-1 x_k (0 where none is stored: its rows are 0), the
    buffered z_{k-q} = H F(k-q, k)^-1 x_k (0 before instant 0: s0's buffer is 0). Then
    T_k D_{k-1} + (U_k H - D_k) F_k = 0, so s - D x stays of the size of the errors, where
    with D = 0 the exact analysis subtracts numbers of the size of the truth's covariance."""
    M, L = sval.shape
    W = L - 2
    D = np.zeros((M, lay.d, lay.n))
    D[:, : lay.n] = trans.gathered(tau, k, of=trans.back)[0]
    for q in range(min(W, k) + 1):
        D[:, lay.stored(q)] = trans.back(k - q, k)[0] * sval[:, W + 1 - q, None, None]
        if q < W:
            D[:, lay.buffered(q)] = H @ trans.back(k - q, k)[0]
    return D


def _keep_window(sx, sP, sval, b: int, base: int, trans: Transitions) -> None:
    """Keep the stored estimates a later OOSM can need (taken at b or later): those from b on,
    and the newest older one moved to b by prediction (no update between: the same equivalent
    measurement), so that every one sits in the plan's window. In place, per run."""
    rb = b - base
    if rb >= sval.shape[1]:  # W = 0: no reading is ever out of sequence, none is kept
        sval[:] = False
        return
    if b < 0:
        return
    has = sval[:, : rb + 1].any(axis=1)
    older = np.flatnonzero(has)
    tb = _last_valid(sval[older, : rb + 1])
    move = older[tb < rb]
    if len(move):
        src = tb[tb < rb]
        F, Q = trans.gathered(src + base, b)
        sx[move, rb] = F @ sx[move, src]
        sP[move, rb] = sym(F @ sP[move, src] @ mT(F)) + Q
        sval[move, rb] = True
    sval[:, :rb] = False


def retrodict_maps(
    system: System, present: np.ndarray, arrive: np.ndarray, sensors: list[int], W: int
) -> tuple[list[tuple[np.ndarray, ...]], bool]:
    """The (T, U, O, P, D) (`StepMap`'s fields) of every step of the retrodicting filter on
    `sensors`, and whether they are per run: `present` (K+1, m) or (M, K+1, m), `arrive`
    (K+1, S) or (M, K+1, S) the instant each reading arrives by; the recursion runs once on
    the distinct patterns."""
    trans = Transitions(system)
    if present.ndim == 2 and arrive.ndim == 2:
        maps = _batch(system, present[None], arrive[None], sensors, W, trans)
        return [tuple(f[0] for f in mk) for mk in maps], False
    M = np.broadcast_shapes(present.shape[:-2], arrive.shape[:-2])[0]
    pres = np.broadcast_to(present, (M,) + present.shape[-2:])
    arr = np.broadcast_to(arrive, (M,) + arrive.shape[-2:])
    # only the sensors the filter fuses make its pattern
    cols = np.zeros(system.m, dtype=bool)
    for j in sensors:
        cols[system.sensor_slices[j]] = True
    key = np.concatenate([pres[..., cols].reshape(M, -1), arr[..., sensors].reshape(M, -1)], 1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    if len(first) == M:  # every run its own pattern (random delays): no copy to gather them
        return _batch(system, np.ascontiguousarray(pres), arr, sensors, W, trans), True
    maps = _batch(system, pres[first], arr[first], sensors, W, trans)
    inverse = inverse.ravel()
    return [tuple(f[inverse] for f in mk) for mk in maps], True


def retrodict_plan(
    system: System,
    name: str,
    present: np.ndarray,
    arrive: np.ndarray,
    sensors: list[int],
    W: int,
) -> Plan:
    """The retrodicting filter on `sensors` as a plan (`retrodict_maps`): maps shared by all
    runs, or per run."""
    s0, D0 = initial_state(system, W)
    maps, per_run = retrodict_maps(system, present, arrive, sensors, W)
    steps = [StepMap(*mk) for mk in maps]
    return Plan(name, s0, steps, per_run=per_run, D0=D0, complete=False)


def initial_state(system: System, W: int) -> tuple[np.ndarray, np.ndarray]:
    """s_0 before step 0 (the prior's mean as the current estimate) and its error form D_0."""
    n = system.n
    lay = _Layout(n, system.m, W)
    assert system.prior is not None
    s0 = np.zeros(lay.d)
    s0[:n] = system.prior.mean
    s0[lay.stored(0)] = system.prior.mean  # unused: instant 0's stored estimate is cur's
    return s0, initial_error_form(lay.d, n)


def initial_error_form(d: int, n: int) -> np.ndarray:
    """D_0 of the state before step 0 (`_error_form`): its current estimate is the prior's
    mean, of x_0 (step 0 has no prediction); nothing stored nor buffered yet."""
    D0 = np.zeros((d, n))
    D0[:n] = np.eye(n)
    return D0
