"""The fusion architectures of Ajgl-Simandl-Dunik (Sec. V) as per-step linear maps.

Every architecture here is linear in the data once its gains are fixed, and its gains depend only
on the model and on which measurements are present, not on the measured values. So each one is
compiled into a *plan*: for every step k an affine map on the estimator's internal state s,

    s_k = T_k s_{k-1} + U_k z_k,        x_hat_k = O_k s_k,        P_k (the covariance it reports)

where z_k is the stacked measurement of eq. (30). Applying a plan to M runs is one matrix product
per step (the shared-gain fast path). When runs differ in which measurements are present (NaN =
missing), the same code builds the maps with a leading run dimension (the per-run path). And because
the maps are explicit, `core.exact` propagates the true error covariance through them exactly.

The internal state s is the mean of each filter, or, while a filter started without a prior has not
yet gathered enough information for a covariance to exist, its information vector y = P^-1 x.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from functools import lru_cache

import numpy as np

from .fusion import ci_omegas, gmf_weight_matrix
from .kalman import gain, joseph
from .linalg import apply, inv_or_nan, is_invertible, mT, spd_inv, sym
from .model import System
from .names import parse_arch


@dataclass
class StepMap:
    """Affine map of one step: s_k = T s_{k-1} + U z_k, x_hat = O s_k, reported covariance P."""

    T: np.ndarray  # (..., d, d_prev)
    U: np.ndarray  # (..., d, m)
    O: np.ndarray  # (..., n, d)
    P: np.ndarray  # (..., n, n)
    # s = D x when the estimator knows the state exactly (I for a mean, Y for an information
    # vector): lets the exact analysis work with s - D x, which stays small when x grows.
    D: np.ndarray | None = None  # (..., d, n)


@dataclass
class SmootherMaps:
    """Backward information filter and forward/backward fusion of FBS, eqs. (25)-(28).

    y_b[K] = 0;  y_b[k] = L[k] (y_b[k+1] + V[k+1] z[k+1]);  x_hat[k] = A[k] s_f[k] + B[k] y_b[k].
    """

    L: list[np.ndarray]  # k = 0..K-1
    V: list[np.ndarray]  # k = 0..K (V[0] unused)
    A: list[np.ndarray]
    B: list[np.ndarray]
    P: list[np.ndarray]


@dataclass
class Plan:
    """A compiled architecture: initial internal state and the per-step maps."""

    name: str
    s0: np.ndarray  # (d0,)
    steps: list[StepMap]
    smoother: SmootherMaps | None = None
    per_run: bool = False
    info: dict = field(default_factory=dict)
    D0: np.ndarray | None = None  # (d0, n): D of the initial state s0
    system: System | None = None  # the model the plan was built for

    @property
    def reported_cov(self) -> np.ndarray:
        """(K+1, n, n) shared or (M, K+1, n, n) per run; NaN where the estimate is undefined."""
        Ps = self.smoother.P if self.smoother is not None else [st.P for st in self.steps]
        return np.stack(Ps, axis=-3)


@dataclass
class Estimate:
    """An architecture's output for M runs: mean (M, K+1, n); cov (K+1, n, n) or (M, K+1, n, n)."""

    mean: np.ndarray
    cov: np.ndarray

    @property
    def shared_cov(self) -> bool:
        return self.cov.ndim == 3


# --------------------------------------------------------------------------------------------
# Building blocks


def _bc(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """np.broadcast_to, skipped when nothing is to be done (it costs microseconds per call, and
    plan building calls it a dozen times a step)."""
    return a if a.shape == shape else np.broadcast_to(a, shape)


def _masked(H: np.ndarray, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H and R with absent rows made information-free: the row of H is zeroed and the absent
    component decoupled with unit variance, so its gain column is exactly zero."""
    if p.shape == H.shape[:-1] and p.all():  # nothing absent, and no per-run pattern
        return H, R
    pf = p.astype(float)
    Hm = H * pf[..., :, None]
    Rm = R * (pf[..., :, None] * pf[..., None, :]) + np.eye(R.shape[-1]) * (1.0 - pf)[..., None, :]
    return Hm, Rm


@dataclass
class _Rows:
    """The measurement components a filter uses: its H and R, and where they sit in the stacked
    measurement z_k of eq. (30).

    A stack of S local filters, one per sensor, carries a leading axis S, padded to the largest
    sensor dimension with components that carry no information: a zero row of H with unit,
    uncorrelated variance, which is what `_masked` makes of an absent component. Their gain
    columns are exactly zero and masking leaves them as they are (so their `cols` entry is an
    arbitrary 0), and one batched computation serves sensors of different sizes.
    """

    H: np.ndarray  # ([S,] r, n)
    R: np.ndarray  # ([S,] r, r)
    cols: np.ndarray  # ([S,] r): index of each component in z_k
    E: np.ndarray  # ([S,] r, m): 0/1 placement, K E puts the columns of a gain K at its rows
    _masks: dict[bytes, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @classmethod
    def of(cls, sys: System, rows: np.ndarray, R: np.ndarray) -> _Rows:
        """One filter on the components `rows` of z_k, believing noise covariance R."""
        return cls(sys.H[rows], R, rows, np.eye(sys.m)[rows])

    @classmethod
    def per_sensor(cls, sys: System) -> _Rows:
        """A stack of one filter per sensor j, each with its own H_j and R_j."""
        S, m = len(sys.sensors), sys.m
        r = max(sen.dim for sen in sys.sensors)
        H = np.zeros((S, r, sys.n))
        R = np.tile(np.eye(r), (S, 1, 1))
        cols = np.zeros((S, r), dtype=int)
        E = np.zeros((S, r, m))
        for j, (sen, sl) in enumerate(zip(sys.sensors, sys.sensor_slices, strict=True)):
            d = sen.dim
            H[j, :d], R[j, :d, :d] = sen.H, sen.R
            cols[j, :d] = np.arange(m)[sl]
            E[j, np.arange(d), cols[j, :d]] = 1.0
        return cls(H, R, cols, E)

    def masked(self, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`_masked` H and R for the present components of z_k (`present`, batch + (m,)). A
        pattern shared by all runs usually recurs every step: its matrices are kept."""
        if present.ndim > 1:
            return _masked(self.H, self.R, present[..., self.cols])
        key = present.tobytes()
        if key not in self._masks:
            self._masks[key] = _masked(self.H, self.R, present[self.cols])
        return self._masks[key]


@dataclass
class _Step:
    T: np.ndarray
    U: np.ndarray  # (..., n, m), embedded
    O: np.ndarray
    P: np.ndarray
    # Error propagation of this filter's generalised error g (error x - x_hat in mean form,
    # information error y - Y x in information form): g^- = Phi g + Gam w ; g = Psi g^- + Lam v.
    Phi: np.ndarray
    Gam: np.ndarray
    Psi: np.ndarray
    Lam: np.ndarray  # (..., n, m), embedded
    D: np.ndarray  # (..., n, n): see StepMap.D


def _merge(parts: list[tuple[np.ndarray, _Step]], shape: tuple[int, ...]) -> _Step:
    """The step of a stack of filters (batch + (S,) = `shape`) from the steps of parts of it,
    given as (indices of the local filters, their step)."""
    out = {}
    for f in fields(_Step):
        first = getattr(parts[0][1], f.name)
        arr = np.empty(shape + first.shape[-2:])
        for j, st in parts:
            arr[..., j, :, :] = getattr(st, f.name)
        out[f.name] = arr
    return _Step(**out)


@dataclass
class _Part:
    """What a step of some filters needs: their matrices (covariance, or information matrix in
    information form), H and R this step (`_masked`), placement E (see `_Rows`), and their
    identity and zero maps, shaped once rather than broadcast at every step. For a stack the
    local axis is the third-last of every array."""

    mat: np.ndarray
    H: np.ndarray
    R: np.ndarray
    E: np.ndarray
    I: np.ndarray  # noqa: E741
    Z: np.ndarray

    def take(self, j: np.ndarray) -> _Part:
        """The local filters j of a stack."""
        mats = (self.mat, self.H, self.R, self.E, self.I, self.Z)
        return _Part(*(a[..., j, :, :] for a in mats))


class _KF:
    """Kalman filters on parts of the stacked measurement, eqs. (14)-(18), Joseph form: one
    filter, or a stack of S local filters (one per sensor, `_Rows.per_sensor`) whose steps are
    computed together, as batched arrays batch + (S, ., .).

    Without a prior a filter runs in information form from zero information, exactly, and
    switches to covariance form at the first step where its information matrix is invertible
    for every run; in a stack, each local filter switches on its own.
    """

    def __init__(self, sys: System, rows: _Rows, batch: tuple[int, ...]):
        n = sys.n
        self.F, self.GQG = sys.F, sys.GQG
        self.rows = rows
        self.eye = np.eye(n)
        local = rows.H.shape[:-2]  # (S,) for a stack, () for one filter
        self.n_local = len(local)
        self.I = _bc(self.eye, local + (n, n))
        self.Z = _bc(np.zeros((n, n)), local + (n, n))
        S = int(np.prod(local, dtype=int))
        shape = batch + local + (n, n)
        # `info` (a flag per filter) and `mat` (see _Part) are replaced at every step, never
        # modified in place.
        if sys.prior is not None:
            self.info = np.zeros(local, dtype=bool)
            self.mat = _bc(sys.prior.cov, shape).copy()
            self.s0 = np.tile(np.asarray(sys.prior.mean, float), S)
            self.D0 = np.tile(np.eye(n), (S, 1))
        else:
            self.info = np.ones(local, dtype=bool)
            self.mat = np.zeros(shape)
            self.s0 = np.zeros(S * n)
            self.D0 = np.zeros((S * n, n))
            if abs(np.linalg.det(sys.F)) < 1e-300:
                raise ValueError("without a prior, F must be invertible (information-form start)")
            self.Finv = np.linalg.inv(sys.F)

        # Whether a filter is still in information form (has no covariance yet).
        self.any_info = bool(self.info.any())

    def step(self, present: np.ndarray, first: bool) -> _Step:
        """Step k of every filter, with the components `present` (batch + (m,)) of z_k."""
        Hk, Rk = self.rows.masked(present)
        part = _Part(self.mat, Hk, Rk, self.rows.E, self.I, self.Z)
        if not self.any_info:  # the usual case: all in covariance form, and they stay so
            st, self.mat, _ = self._step_cov(part, first)
            return st
        if self.info.all():  # all in information form: one batched step
            st, self.mat, self.info = self._step_info(part, first)
            self.any_info = bool(self.info.any())
            return st
        # Local filters in different forms (no prior, and one local could invert its
        # information earlier than another): each group in its own form, then put together.
        mat, info, parts = np.empty_like(self.mat), self.info.copy(), []
        for form in (False, True):
            j = np.flatnonzero(self.info == form)
            st, mat[..., j, :, :], info[j] = self._step(form, part.take(j), first)
            parts.append((j, st))
        self.mat, self.info, self.any_info = mat, info, bool(info.any())
        return _merge(parts, mat.shape[:-2])

    def _step(self, info: bool, part: _Part, first: bool) -> tuple[_Step, np.ndarray, np.ndarray]:
        """One step of filters all in information form (`info`) or all in covariance form:
        their step, their new matrices and their new forms."""
        return self._step_info(part, first) if info else self._step_cov(part, first)

    def _step_cov(self, part: _Part, first: bool) -> tuple[_Step, np.ndarray, np.ndarray]:
        if first:
            Pp, Tp, Gam = part.mat, self.eye, part.Z
        else:
            Pp, Tp, Gam = sym(self.F @ part.mat @ self.F.T + self.GQG), self.F, part.I
        K = gain(Pp, part.H, part.R)
        IKH = self.eye - K @ part.H
        P = joseph(Pp, K, part.H, part.R, IKH)
        Ke = K @ part.E  # exact: each column of K E is one column of K, or zero
        info = np.zeros(P.shape[P.ndim - 2 - self.n_local : -2], dtype=bool)
        return _Step(IKH @ Tp, Ke, part.I, P, Tp, Gam, IKH, -Ke, part.I), P, info

    def _step_info(self, part: _Part, first: bool) -> tuple[_Step, np.ndarray, np.ndarray]:
        Y, Hk = part.mat, part.H
        if first:
            A, Yp, Gam = self.eye, Y, part.Z
        else:
            # Prediction in information form valid for singular Y (and singular Q):
            # with M = F^-T Y F^-1, Y^- = (I + M GQG)^-1 M and y^- = (I + M GQG)^-1 F^-T y.
            Mi = self.Finv.T @ Y @ self.Finv
            Bm = self.eye + Mi @ self.GQG
            A = np.linalg.solve(Bm, _bc(self.Finv.T, Bm.shape))
            Yp = sym(np.linalg.solve(Bm, Mi))
            Gam = -(A @ Y @ self.Finv)
        RiH = np.linalg.solve(part.R, Hk)
        Y = sym(Yp + mT(Hk) @ RiH)
        Ue = mT(RiH) @ part.E
        ok = is_invertible(Y)
        # A filter switches to covariance form when its Y is invertible in every run.
        switch = np.all(ok, axis=tuple(range(ok.ndim - self.n_local)))
        if switch.all():
            P = spd_inv(Y)
            step = _Step(P @ A, P @ Ue, part.I, P, A, Gam, -P, -(P @ Ue), part.I)
            return step, P, ~switch
        Pinv = inv_or_nan(Y, axes=tuple(range(-self.n_local, 0)))  # per filter, as alone
        step = _Step(A, Ue, Pinv, Pinv, A, Gam, _bc(self.eye, Y.shape), Ue, Y)
        if not switch.any():
            return step, Y, ~switch
        # Some local filters of a stack switch now, the others later. For the former,
        # inv_or_nan gave spd_inv(Y), as above.
        P = Pinv
        cov = _Step(P @ A, P @ Ue, part.I, P, A, Gam, -P, -(P @ Ue), part.I)
        w = switch[:, None, None]
        step = _Step(
            *(np.where(w, getattr(cov, f.name), getattr(step, f.name)) for f in fields(_Step))
        )
        return step, np.where(w, P, Y), ~switch


class _Steady:
    """Detects the steady state of a Riccati recursion so that long horizons reuse one map.

    With every measurement present and a time-invariant model, once the covariance state after
    step k equals the one after step k-1 (to rounding, 1e-15 relative), every later step's map is
    the same as step k's: the plan repeats it instead of recomputing 10^5 identical gains.
    """

    def __init__(self, present: np.ndarray):
        self.enabled = present.ndim == 2 and bool(present.all())
        self.prev: np.ndarray | None = None

    def reached(self, *mats: np.ndarray) -> bool:
        if not self.enabled:
            return False
        cur = mats[0].ravel() if len(mats) == 1 else np.concatenate([m.ravel() for m in mats])
        hit = self.prev is not None and np.abs(cur - self.prev).max() <= 1e-15 * np.abs(cur).max()
        self.prev = cur
        return bool(hit)


def _fill(steps: list, total: int) -> None:
    """Repeat the last (steady-state) element until the list has `total` entries."""
    steps.extend([steps[-1]] * (total - len(steps)))


def _block_diag(mats: list[np.ndarray]) -> np.ndarray:
    batch = np.broadcast_shapes(*(m.shape[:-2] for m in mats))
    rows = sum(m.shape[-2] for m in mats)
    cols = sum(m.shape[-1] for m in mats)
    out = np.zeros(batch + (rows, cols))
    r = c = 0
    for m in mats:
        out[..., r : r + m.shape[-2], c : c + m.shape[-1]] = m
        r, c = r + m.shape[-2], c + m.shape[-1]
    return out


def _stack_diag(X: np.ndarray) -> np.ndarray:
    """Block-diagonal matrix of a stack: (..., S, a, b) -> (..., S a, S b)."""
    *lead, S, a, b = X.shape
    out = np.zeros((*lead, S, a, S, b))
    i = np.arange(S)
    out[..., i, :, i, :] = np.moveaxis(X, -3, 0) if lead else X  # the index puts S first
    return out.reshape((*lead, S * a, S * b))


def _stack_rows(X: np.ndarray) -> np.ndarray:
    """A stack's matrices one above the other: (..., S, a, b) -> (..., S a, b)."""
    *lead, S, a, b = X.shape
    return X.reshape((*lead, S * a, b))


def _stack_cols(X: np.ndarray) -> np.ndarray:
    """A stack's matrices side by side: (..., S, a, b) -> (..., a, S b)."""
    *lead, S, a, b = X.shape
    return X.swapaxes(-3, -2).reshape((*lead, a, S * b))


def _sum_after(a: np.ndarray, X: np.ndarray) -> np.ndarray:
    """a + X_1 + ... + X_S for a stack X (..., S, p, q), added in that order (a numpy sum over
    a leading axis adds sequentially), as a sum over the sensors written out would."""
    return np.concatenate([a[..., None, :, :], X], axis=-3).sum(axis=-3)


def _blockdiag_R(sys: System) -> np.ndarray:
    """R of eq. (31) without cross-covariances: what architectures that assume independent
    sensor noise (HKF's equivalent measurements) believe."""
    return _block_diag([s.R for s in sys.sensors])


# --------------------------------------------------------------------------------------------
# Architectures


def _single_filter_plan(name: str, sys: System, rows: np.ndarray, present: np.ndarray) -> Plan:
    batch = present.shape[:-2]
    kf = _KF(sys, _Rows.of(sys, rows, sys.R[np.ix_(rows, rows)]), batch)
    s0 = kf.s0
    steps = []
    infos: list[np.ndarray | None] = []
    steady = _Steady(present)
    K1 = present.shape[-2]
    for k in range(K1):
        st = kf.step(present[..., k, :], first=(k == 0))
        steps.append(StepMap(st.T, st.U, st.O, st.P, st.D))
        infos.append(kf.mat if kf.any_info else None)
        if not kf.any_info and steady.reached(kf.mat):
            _fill(steps, K1)
            _fill(infos, K1)
            break
    return Plan(name, s0, steps, per_run=bool(batch), info={"Y": infos}, D0=kf.D0)


def _hkf_plan(sys: System, present: np.ndarray) -> Plan:
    """Hierarchical KF with feedback, eqs. (36)-(40).

    Each local KF j restarts from the fused prediction (38), updates with its own sensor, and the
    fusion centre adds the equivalent measurements P_j^-1 x_j - P^-1_pred x_pred (36)-(37). The
    S local updates are one batched computation on the stacked sensors (`_Rows.per_sensor`).
    """
    batch = present.shape[:-2]
    n, m = sys.n, sys.m
    S = len(sys.sensors)
    F, GQG = sys.F, sys.GQG
    eye = np.eye(n)
    # Before a covariance exists (no prior), local equivalent measurements are just
    # H_j^T R_j^-1 H_j: the fused information filter on block-diagonal R is exactly that.
    front = _KF(sys, _Rows.of(sys, np.arange(m), _blockdiag_R(sys)), batch)
    sensors = _Rows.per_sensor(sys)
    s0 = front.s0
    steps = []
    P = None
    steady = _Steady(present)
    K1 = present.shape[-2]
    for k in range(K1):
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
        Yp = spd_inv(Pp)
        Hj, Rj = sensors.masked(present[..., k, :])  # batch + (S, r, .)
        Ppj = Pp[..., None, :, :]  # every local starts from the fused prediction
        Kj = gain(Ppj, Hj, Rj)
        IKH = eye - Kj @ Hj
        Yj = spd_inv(joseph(Ppj, Kj, Hj, Rj, IKH))
        Yf = _sum_after((1 - S) * Yp, Yj)
        Tacc = _sum_after((1 - S) * Yp, Yj @ IKH)
        # Each sensor's gain sits in its own columns of z_k, zero elsewhere: the sum is exact.
        U = (Yj @ Kj @ sensors.E).sum(axis=-3)
        P = spd_inv(Yf)
        steps.append(StepMap(P @ Tacc @ Tp, P @ U, _bc(eye, P.shape), P, eye))
        if steady.reached(P):
            _fill(steps, K1)
            break
    return Plan("HKF", s0, steps, per_run=bool(batch), D0=front.D0)


def _track_to_track_plan(name: str, sys: System, present: np.ndarray, criterion: str) -> Plan:
    """Local KFs without feedback fused by Millman (MSC, eqs. 32-34), by the generalised Millman
    formula with exact cross-covariances (MSC-GMF, eqs. 6-7 and 35), by covariance intersection
    (CI) or by the plain average with its true covariance (AVG).

    The local filters' joint error covariance follows eq. (35), extended by K_i R_ij K_j^T for
    correlated sensor noise and by information-form errors for filters started without a prior.
    The local filters run as one stack (`_KF` on `_Rows.per_sensor`); the fusion rules, which do
    not feed back, are evaluated for all steps together after the recursion.
    """
    batch = present.shape[:-2]
    n, m = sys.n, sys.m
    S = len(sys.sensors)
    GQG = sys.GQG
    locs = _KF(sys, _Rows.per_sensor(sys), batch)
    everything = _Rows.of(sys, np.arange(m), sys.R)  # masked per step for eq. (35)
    if sys.prior is not None:
        J = _bc(np.kron(np.ones((S, S)), sys.prior.cov), batch + (S * n, S * n)).copy()
    else:
        J = np.zeros(batch + (S * n, S * n))
    # Only the generalised Millman formula and the average's honest covariance need the
    # cross-covariances of eq. (35).
    joint = name in ("MSC-GMF", "AVG")
    stack = batch + (S, n, n)
    # When every local is in covariance form they all predict with F and the full process
    # noise: Phi and Gam of eq. (35), and the noise term, are then the same at every step.
    Phi_cov = _stack_diag(_bc(sys.F, (S, n, n)))
    Gam_cov = D_cov = _stack_rows(locs.I)  # and D_j = I
    GQG_cov = Gam_cov @ GQG @ mT(Gam_cov)
    steps = []
    # After each computed step: the locals' forms, their matrices (covariance, or information
    # in information form), J, and their readouts x_j = O_j s_j.
    after: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    steady = _Steady(present)
    K1 = present.shape[-2]
    for k in range(K1):
        first = k == 0
        st = locs.step(present[..., k, :], first)
        if joint:
            if not first and st.Phi is locs.F:  # every local predicted in covariance form
                J = Phi_cov @ J @ mT(Phi_cov) + GQG_cov
            elif not first:
                Phi = _stack_diag(_bc(st.Phi, stack))
                Gam = _stack_rows(_bc(st.Gam, stack))
                J = Phi @ J @ mT(Phi) + Gam @ GQG @ mT(Gam)
            Psi = _stack_diag(_bc(st.Psi, stack))
            Lam = _stack_rows(st.Lam)
            _, Rk = everything.masked(present[..., k, :])
            J = sym(Psi @ J @ mT(Psi) + Lam @ Rk @ mT(Lam))
        T = _stack_diag(_bc(st.T, stack))
        # A local's state s_j is D_j x + sigma_j with sigma_j = -g_j (mean form: s = x_hat,
        # g = x - x_hat) or +g_j (information form: s = y, g = y - Y x); J is cov(g).
        D = D_cov if st.D is locs.I else _stack_rows(_bc(st.D, stack))  # D_j = I: mean form
        steps.append(StepMap(T, _stack_rows(st.U), None, None, D))  # O, P: below
        after.append((locs.info, locs.mat, J, st.O))
        if not locs.any_info and steady.reached(J if joint else locs.mat):
            _fill(steps, K1)
            break
    computed = steps[: len(after)]  # the rest repeat the last one
    forms = np.stack([a[0] for a in after])  # (L, S)
    info = {}
    if name == "MSC":
        O, P = _msc_readouts(forms, np.stack([a[1] for a in after]))
        _set_readouts(computed, O, P)
    elif name == "MSC-GMF":
        for sm, (form, _, J, _) in zip(computed, after, strict=True):
            # Eqs. (2)-(7) with the unbiasedness constraint sum_j c_j D_j = I, which is eq. (7)
            # when every local is in mean form (D_j = I) and extends it to information form.
            # One call per step: lstsq (the shared path's solver) does not batch.
            if not form.any():
                sm.O, sm.P = gmf_weight_matrix(J, n)  # sign = -I cancels
            else:
                sign = _signs(tuple(form.tolist()), n)
                sm.O, sm.P = gmf_weight_matrix(sign @ J @ sign, n, sm.D)
    elif name == "AVG":
        # Equal weights on the local means (eq. 2, c_i = I/S) and the covariance they really
        # give, eq. (4); undefined (NaN) while a local has no mean yet.
        O = _stack_cols(np.stack([_bc(a[3], stack) for a in after])) / S
        sign = np.stack([_signs(tuple(f.tolist()), n) for f in forms])
        Msig = O @ sign.reshape(sign.shape[:1] + (1,) * len(batch) + sign.shape[1:])
        P = sym(Msig @ np.stack([a[2] for a in after]) @ mT(Msig))
        _set_readouts(computed, O, P)
    else:  # CI: the omegas of all steps in one go
        Ys, Ws = _local_infos(forms, np.stack([a[1] for a in after]))
        info["omega"] = _ci_readouts(steps, Ys, Ws, batch, criterion)
    return Plan(name, locs.s0, steps, per_run=bool(batch), info=info, D0=locs.D0)


def _set_readouts(steps: list[StepMap], O: np.ndarray, P: np.ndarray) -> None:
    """Readout O and reported covariance P of each step from arrays over the steps (L, ...)."""
    for i, st in enumerate(steps):
        st.O, st.P = O[i], P[i]


@lru_cache(maxsize=64)
def _signs(info: tuple[bool, ...], n: int) -> np.ndarray:
    """diag(+I for a local in information form, -I in mean form): sigma = sign g."""
    return np.kron(np.diag([1.0 if i else -1.0 for i in info]), np.eye(n))


def _local_infos(forms: np.ndarray, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each local's information matrix Y_j and the map W_j with Y_j x_j = W_j s_j, for L steps
    at once: forms (L, S), mats (L,) + batch + (S, n, n). In covariance form Y_j = P_j^-1 = W_j;
    in information form the state is the information vector itself: Y_j is the matrix the
    filter carries and W_j = I."""
    if not forms.any():
        Y = spd_inv(mats)
        return Y, Y
    # Steps and locals side by side, (L, S) + batch + (n, n), to pick them by their form.
    M = np.moveaxis(mats, -3, 1)
    Y = np.empty_like(M)
    Y[~forms] = spd_inv(M[~forms])
    Y[forms] = M[forms]
    W = Y.copy()
    W[forms] = np.eye(mats.shape[-1])
    return np.moveaxis(Y, 1, -3), np.moveaxis(W, 1, -3)


def _msc_readouts(forms: np.ndarray, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Millman fusion (33)-(34) in information form for L steps at once: P^-1 = sum Y_j,
    x = P sum Y_j x_j, where Y_j x_j is the information vector itself for a local still in
    information form. Returns O (L,) + batch + (n, S n) and P (L,) + batch + (n, n)."""
    Ys, Ws = _local_infos(forms, mats)
    P = inv_or_nan(Ys.sum(axis=-3), axes=(0,))  # each step on its own
    return _stack_cols(P[..., None, :, :] @ Ws), P


def _ci_readouts(
    steps: list[StepMap], Ys: np.ndarray, Ws: np.ndarray, batch: tuple[int, ...], criterion: str
) -> np.ndarray:
    """Covariance intersection of the local estimates at the first L steps, given the local
    informations Y_j and maps W_j with Y_j x_j = W_j s_j, (L,) + batch + (S, n, n): every step's
    (and run's) omega in one `ci_omegas` call, then P = (sum w_j Y_j)^-1 and the weights
    w_j P W_j written into those steps' maps. In information form a local with too little
    information to have a mean of its own still contributes. Returns the omegas, batch +
    (K+1, S)."""
    K1 = len(steps)
    L, S, n = Ys.shape[0], Ys.shape[-3], Ys.shape[-1]
    om = ci_omegas(Ys.reshape((-1, S, n, n)), criterion).reshape(Ys.shape[:-2])
    P = inv_or_nan(np.einsum("...j,...jab->...ab", om, Ys))
    O = np.concatenate([om[..., j, None, None] * (P @ Ws[..., j, :, :]) for j in range(S)], -1)
    by_id = {}
    for i in range(L):
        steps[i].O, steps[i].P = O[i], P[i]
        by_id[id(steps[i])] = om[i]
    omega = np.full((K1,) + batch + (S,), np.nan)
    for k, st in enumerate(steps):
        if id(st) in by_id:
            omega[k] = by_id[id(st)]
    return np.moveaxis(omega, 0, -2)


def _fbs_plan(sys: System, present: np.ndarray) -> Plan:
    """Fixed-interval smoother, eqs. (25)-(28): the forward KF on all sensors fused by Millman's
    formula with a backward information filter started from zero information.

    Backward filter: S^+ = S_{k+1} + H^T R^-1 H, y^+ = y_{k+1} + H^T R^-1 z_{k+1} (data at k+1),
    then
    back through the dynamics, S_k = F^T (I + S^+ GQG)^-1 S^+ F and y_k = F^T (I + S^+ GQG)^-1 y^+.
    """
    fwd = _single_filter_plan("FBS", sys, np.arange(sys.m), present)
    batch = present.shape[:-2]
    n = sys.n
    eye = np.eye(n)
    K1 = present.shape[-2]
    V: list[np.ndarray] = [np.zeros(0)] * K1
    L: list[np.ndarray] = [np.zeros(0)] * (K1 - 1)
    Smat = [np.zeros(batch + (n, n)) for _ in range(K1)]
    steady = _Steady(present)
    everything = _Rows.of(sys, np.arange(sys.m), sys.R)
    GQG = sys.GQG
    for k in range(K1 - 1, -1, -1):
        if steady.enabled and k < K1 - 3 and Smat[k + 1] is Smat[k + 2]:
            V[k], L[k], Smat[k] = V[k + 1], L[k + 1], Smat[k + 1]
            continue
        Hk, Rk = everything.masked(present[..., k, :])
        RiH = np.linalg.solve(Rk, Hk)
        V[k] = mT(RiH)
        if k < K1 - 1:
            Hn = everything.masked(present[..., k + 1, :])[0]
            Splus = sym(Smat[k + 1] + mT(Hn) @ mT(V[k + 1]))
            Bm = eye + Splus @ GQG
            # L = F^T (I + S^+ GQG)^-1, computed as a solve with the transpose.
            L[k] = mT(np.linalg.solve(mT(Bm), _bc(sys.F, Bm.shape)))
            Smat[k] = sym(L[k] @ Splus @ sys.F)
            if steady.reached(Smat[k]):
                Smat[k] = Smat[k + 1]
    A, B, Ps = [], [], []
    for k, st in enumerate(fwd.steps):
        Sk = Smat[k]
        Yf = fwd.info["Y"][k]
        if k > 0 and st is fwd.steps[k - 1] and Sk is Smat[k - 1]:
            A.append(A[-1])
            B.append(B[-1])
            Ps.append(Ps[-1])
            continue
        if Yf is None:
            PS = st.P @ Sk
            Ks = mT(np.linalg.solve(mT(eye + PS), mT(PS)))  # eq. (26)
            Pk = sym((eye - Ks) @ st.P)  # eq. (27)
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


def build_plan(
    sys: System, arch: str, steps: int, present: np.ndarray | None = None, criterion: str = "trace"
) -> Plan:
    """Compile architecture `arch` for instants k = 0..steps.

    `present` is a boolean mask of measurement components, (K+1, m) shared by all runs or
    (M, K+1, m) per run; None means every measurement is present.
    """
    base, sensor = parse_arch(arch, [s.name for s in sys.sensors])
    if present is None:
        present = np.ones((steps + 1, sys.m), dtype=bool)
    if base == "CKF":
        plan = _single_filter_plan("CKF", sys, np.arange(sys.m), present)
    elif base == "SKF":
        j = sys.sensor_index(sensor)
        plan = _single_filter_plan(arch, sys, np.arange(sys.m)[sys.sensor_slices[j]], present)
    elif base == "HKF":
        plan = _hkf_plan(sys, present)
    elif base in ("MSC", "MSC-GMF", "CI", "AVG"):
        plan = _track_to_track_plan(base, sys, present, criterion)
    elif base == "FBS":
        plan = _fbs_plan(sys, present)
    else:
        raise AssertionError(base)
    plan.system = sys
    return plan


#: Horizons up to this many instants apply a shared plan as one dense linear map (below).
DENSE_MAX_STEPS = 128


def run_plan(plan: Plan, z: np.ndarray) -> Estimate:
    """Apply a plan to measurements z (M, K+1, m); NaN entries must be absent in the plan's mask.

    A shared plan over a short horizon is one affine map of the whole measurement history,
    mean = W vec(z) + c, applied to all runs as a single GEMM on the contiguous (M, (K+1) m)
    view of z. W and c are the plan's responses to unit measurements and to no data, obtained by
    running the step recursion on a basis, so both routes compute the same linear map.
    Longer horizons and per-run plans run the step recursion itself.
    """
    M, K1, m = z.shape
    if plan.per_run or K1 > DENSE_MAX_STEPS:
        return Estimate(_recursion(plan, np.where(np.isnan(z), 0.0, z)), plan.reported_cov)
    if "dense" not in plan.info:
        # The linear part from unit measurements with a zero initial state, the constant from
        # the initial state with no data: no subtraction, so a large prior mean (UTM metres)
        # cannot cancel the small gains away.
        basis = np.eye(K1 * m).reshape(K1 * m, K1, m)
        W = _recursion(plan, basis, np.zeros_like(plan.s0))
        c = _recursion(plan, np.zeros((1, K1, m)))
        plan.info["dense"] = (W.reshape(K1 * m, -1), c.reshape(-1))
    W, c = plan.info["dense"]
    if np.isnan(z).any():  # absent in the plan's own mask: W has zero weight there
        z = np.where(np.isnan(z), 0.0, z)
    mean = np.ascontiguousarray(z).reshape(M, K1 * m) @ W
    mean += c
    return Estimate(mean.reshape(M, K1, -1), plan.reported_cov)


#: A steady tail of a plan run on at most _FEW_RUNS runs goes through in blocks of _BLOCK steps.
_FEW_RUNS = 16
_BLOCK = 32


def _recursion(plan: Plan, z: np.ndarray, s0: np.ndarray | None = None) -> np.ndarray:
    """The step recursion s_k = T s_{k-1} + U z_k, x_k = O s_k (and FBS's backward pass)."""
    M, K1, _ = z.shape
    s0 = plan.s0 if s0 is None else s0
    s = _bc(s0, (M, s0.shape[0]))
    n = plan.steps[0].O.shape[-2]
    out = np.empty((M, K1, n))
    states = [] if plan.smoother is not None else None
    # With few runs the per-step numpy calls, not the arithmetic, are the cost: a long steady
    # tail (a 10^5-step log) is run in blocks instead, a few GEMMs for all of it.
    few_runs = not plan.per_run and M <= _FEW_RUNS
    blocks = 0
    if few_runs:
        blocks = (K1 - _steady_from(plan.steps)) // _BLOCK
        blocks = blocks if blocks >= 2 else 0
    head = K1 - blocks * _BLOCK
    for k in range(head):
        st = plan.steps[k]
        s = apply(st.T, s) + apply(st.U, z[:, k])
        if states is not None:
            states.append(s)
        else:
            out[:, k] = apply(st.O, s)
    if blocks:
        st = plan.steps[-1]
        tail = _steady_states(st.T, st.U, s, z[:, head:])  # (M, blocks * _BLOCK, d)
        if states is not None:
            states.extend(tail[:, j] for j in range(tail.shape[1]))
        else:
            out[:, head:] = tail @ st.O.T
    if plan.smoother is not None:
        _smooth(plan.smoother, states, z, out, few_runs)
    return out


def _smooth(
    sm: SmootherMaps, states: list[np.ndarray], z: np.ndarray, out: np.ndarray, few_runs: bool
) -> None:
    """FBS's backward pass into `out`; its steady middle, with few runs, in blocks as well."""
    M, K1, _ = z.shape
    yb = np.zeros((M, out.shape[-1]))
    a, b = _steady_segment(sm, K1) if few_runs else (0, -1)
    k = K1 - 1
    while k >= 0:
        if k == b:
            # y_b[k] = L y_b[k+1] + (L V) z[k+1] for k = b..a: the forward recursion on the
            # reversed inputs z[b+1], ..., z[a+1]
            Lm = sm.L[b]
            Y = _steady_states(Lm, Lm @ sm.V[b + 1], yb, z[:, b + 1 : a : -1])[:, ::-1]
            S = np.stack(states[a : b + 1], axis=1)
            out[:, a : b + 1] = S @ mT(sm.A[b]) + Y @ mT(sm.B[b])
            yb, k = Y[:, 0], a - 1
            continue
        if k < K1 - 1:
            yb = apply(sm.L[k], yb + apply(sm.V[k + 1], z[:, k + 1]))
        out[:, k] = apply(sm.A[k], states[k]) + apply(sm.B[k], yb)
        k -= 1


def _steady_segment(sm: SmootherMaps, K1: int) -> tuple[int, int]:
    """(a, b): the longest run of steps k <= K-1 with the same backward and fusion maps, cut to
    a multiple of _BLOCK steps (at least two blocks); (0, -1) if there is none."""
    best, start = (0, -1), 0
    for k in range(1, K1 - 1):
        if not (
            sm.L[k] is sm.L[k - 1]
            and sm.V[k + 1] is sm.V[k]
            and sm.A[k] is sm.A[k - 1]
            and sm.B[k] is sm.B[k - 1]
        ):
            start = k
        if k - start > best[1] - best[0]:
            best = (start, k)
    a, b = best
    N = (b - a + 1) // _BLOCK * _BLOCK
    return (b - N + 1, b) if N >= 2 * _BLOCK else (0, -1)


def _steady_from(steps: list[StepMap]) -> int:
    """First k from which every step is the same map (the steady state reused by _Steady)."""
    k = len(steps) - 1
    while k > 0 and steps[k - 1] is steps[-1]:
        k -= 1
    return k


def _steady_states(T: np.ndarray, U: np.ndarray, s: np.ndarray, z: np.ndarray) -> np.ndarray:
    """States s_1..s_N of the time-invariant recursion s_j = T s_{j-1} + U z_j from s (M, d),
    z (M, N, m), N a multiple of _BLOCK = L.

    Within a block, state j (from 0) is T^(j+1) s_init + sum_(i <= j) T^(j-i) U z_i: one GEMM
    gives every block's response to its own inputs, one more adds the response to its initial
    state; only the B block-initial states go through a sequential loop.
    """
    M, N, m = z.shape
    d, L = T.shape[0], _BLOCK
    B = N // L
    Tp = np.empty((L, d, d))  # Tp[j] = T^(j+1)
    Tp[0] = T
    for j in range(1, L):
        Tp[j] = T @ Tp[j - 1]
    TU = np.concatenate([U[None], Tp[:-1] @ U])  # TU[q] = T^q U
    G = np.zeros((L, m, L, d))  # (input i, its component) -> (state j, its component)
    for i in range(L):
        G[i, :, i:, :] = TU[: L - i].transpose(2, 0, 1)
    G = G.reshape(L * m, L * d)
    Phi = Tp.transpose(2, 0, 1).reshape(d, L * d)  # initial state -> the block's states
    S = (np.ascontiguousarray(z).reshape(M, B, L * m) @ G).reshape(M, B, L, d)
    starts = np.empty((M, B, d))
    TL = Tp[-1].T
    for b in range(B):
        starts[:, b] = s
        s = S[:, b, -1] + s @ TL
    S += (starts @ Phi).reshape(M, B, L, d)
    return S.reshape(M, N, d)


def shared_pattern(z: np.ndarray) -> np.ndarray | None:
    """The (K+1, m) mask of present measurements when every run has the same one, else None.

    A pattern shared by all runs (a sensor at half rate, a gap in every run) keeps the
    shared-gain path: one plan built with that mask serves all runs.
    """
    present = ~np.isnan(z)
    return present[0] if (present == present[:1]).all() else None


def estimate(sys: System, z: np.ndarray, arch: str, criterion: str = "trace") -> Estimate:
    """Run architecture `arch` on measurements z (M, K+1, m).

    When every run has the same measurement pattern (usually: all present) the runs share gains
    and covariances (one plan, applied to all runs at once); when runs differ in which
    measurements are missing (NaN), the plan is built per run.
    """
    K = z.shape[1] - 1
    pattern = shared_pattern(z)
    if pattern is not None:
        plan = build_plan(sys, arch, K, None if pattern.all() else pattern, criterion)
    else:
        plan = build_plan(sys, arch, K, ~np.isnan(z), criterion)
    return run_plan(plan, z)
