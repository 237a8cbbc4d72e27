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

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .fusion import ci_omegas, gmf_weights
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
    if p.ndim == 1 and p.all():
        return H, R
    pf = p.astype(float)
    Hm = H * pf[..., :, None]
    Rm = R * (pf[..., :, None] * pf[..., None, :]) + np.eye(R.shape[-1]) * (1.0 - pf)[..., None, :]
    return Hm, Rm


def _embed(block: np.ndarray, rows: np.ndarray, m: int) -> np.ndarray:
    """Place the columns of `block` (..., r, len(rows)) into a (..., r, m) matrix at `rows`."""
    out = np.zeros(block.shape[:-1] + (m,))
    out[..., rows] = block
    return out


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


class _KF:
    """A Kalman filter on a subset `rows` of the stacked measurement, eqs. (14)-(18), Joseph form.

    Without a prior it runs in information form from zero information, exactly, and switches to
    covariance form at the first step where the information matrix is invertible for every run.
    """

    def __init__(self, sys: System, rows: np.ndarray, R: np.ndarray, batch: tuple[int, ...]):
        n = sys.n
        self.F, self.GQG, self.m = sys.F, sys.GQG, sys.m
        self.rows = rows
        self.H = sys.H[rows]
        self.R = R
        self.eye = np.eye(n)
        if sys.prior is not None:
            self.info = False
            self.mat = _bc(sys.prior.cov, batch + (n, n)).copy()
            self.s0 = np.asarray(sys.prior.mean, float)
            self.D0 = np.eye(n)
        else:
            self.info = True
            self.mat = np.zeros(batch + (n, n))
            self.s0 = np.zeros(n)
            self.D0 = np.zeros((n, n))
            if abs(np.linalg.det(sys.F)) < 1e-300:
                raise ValueError("without a prior, F must be invertible (information-form start)")
            self.Finv = np.linalg.inv(sys.F)

    def step(self, present: np.ndarray, first: bool) -> _Step:
        Hk, Rk = _masked(self.H, self.R, present)
        return self._step_info(Hk, Rk, first) if self.info else self._step_cov(Hk, Rk, first)

    def _step_cov(self, Hk: np.ndarray, Rk: np.ndarray, first: bool) -> _Step:
        if first:
            Pp, Tp, Gam = self.mat, self.eye, np.zeros_like(self.eye)
        else:
            Pp, Tp, Gam = sym(self.F @ self.mat @ self.F.T + self.GQG), self.F, self.eye
        K = gain(Pp, Hk, Rk)
        P = joseph(Pp, K, Hk, Rk)
        IKH = self.eye - K @ Hk
        self.mat = P
        Ke = _embed(K, self.rows, self.m)
        return _Step(IKH @ Tp, Ke, self.eye, P, Tp, Gam, IKH, -Ke, self.eye)

    def _step_info(self, Hk: np.ndarray, Rk: np.ndarray, first: bool) -> _Step:
        Y = self.mat
        if first:
            A, Yp, Gam = self.eye, Y, np.zeros_like(self.eye)
        else:
            # Prediction in information form valid for singular Y (and singular Q):
            # with M = F^-T Y F^-1, Y^- = (I + M GQG)^-1 M and y^- = (I + M GQG)^-1 F^-T y.
            Mi = self.Finv.T @ Y @ self.Finv
            Bm = self.eye + Mi @ self.GQG
            A = np.linalg.solve(Bm, _bc(self.Finv.T, Bm.shape))
            Yp = sym(np.linalg.solve(Bm, Mi))
            Gam = -(A @ Y @ self.Finv)
        RiH = np.linalg.solve(Rk, Hk)
        Y = sym(Yp + mT(Hk) @ RiH)
        Ue = _embed(mT(RiH), self.rows, self.m)
        self.mat = Y
        ok = is_invertible(Y)
        if np.all(ok):
            P = spd_inv(Y)
            self.info, self.mat = False, P
            return _Step(P @ A, P @ Ue, self.eye, P, A, Gam, -P, -(P @ Ue), self.eye)
        Pinv = inv_or_nan(Y)
        return _Step(A, Ue, Pinv, Pinv, A, Gam, _bc(self.eye, Y.shape), Ue, Y)


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
        cur = np.concatenate([np.ravel(m) for m in mats])
        hit = self.prev is not None and np.max(np.abs(cur - self.prev)) <= 1e-15 * np.max(
            np.abs(cur)
        )
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


def _blockdiag_R(sys: System) -> np.ndarray:
    """R of eq. (31) without cross-covariances: what architectures that assume independent
    sensor noise (HKF's equivalent measurements) believe."""
    return _block_diag([s.R for s in sys.sensors])


# --------------------------------------------------------------------------------------------
# Architectures


def _single_filter_plan(name: str, sys: System, rows: np.ndarray, present: np.ndarray) -> Plan:
    batch = present.shape[:-2]
    kf = _KF(sys, rows, sys.R[np.ix_(rows, rows)], batch)
    s0 = kf.s0
    steps = []
    infos: list[np.ndarray | None] = []
    steady = _Steady(present)
    K1 = present.shape[-2]
    for k in range(K1):
        st = kf.step(present[..., k, rows], first=(k == 0))
        steps.append(StepMap(st.T, st.U, st.O, st.P, st.D))
        infos.append(kf.mat if kf.info else None)
        if not kf.info and steady.reached(kf.mat):
            _fill(steps, K1)
            _fill(infos, K1)
            break
    return Plan(name, s0, steps, per_run=bool(batch), info={"Y": infos}, D0=kf.D0)


def _hkf_plan(sys: System, present: np.ndarray) -> Plan:
    """Hierarchical KF with feedback, eqs. (36)-(40).

    Each local KF j restarts from the fused prediction (38), updates with its own sensor, and the
    fusion centre adds the equivalent measurements P_j^-1 x_j - P^-1_pred x_pred (36)-(37).
    """
    batch = present.shape[:-2]
    n, m = sys.n, sys.m
    eye = np.eye(n)
    allrows = np.arange(m)
    # Before a covariance exists (no prior), local equivalent measurements are just
    # H_j^T R_j^-1 H_j: the fused information filter on block-diagonal R is exactly that.
    front = _KF(sys, allrows, _blockdiag_R(sys), batch)
    s0 = front.s0
    steps = []
    P = None
    steady = _Steady(present)
    K1 = present.shape[-2]
    for k in range(K1):
        first = k == 0
        if front.info:
            st = front.step(present[..., k, :], first)
            steps.append(StepMap(st.T, st.U, st.O, st.P, st.D))
            P = front.mat
            continue
        if first:
            Pp, Tp = front.mat, eye
        else:
            Pp, Tp = sym(sys.F @ P @ sys.F.T + sys.GQG), sys.F
        Yp = spd_inv(Pp)
        S = len(sys.sensors)
        Yf = (1 - S) * Yp
        Tacc = (1 - S) * Yp
        U = np.zeros(batch + (n, m))
        for j, sl in enumerate(sys.sensor_slices):
            rows = allrows[sl]
            Hj, Rj = _masked(sys.sensors[j].H, sys.sensors[j].R, present[..., k, rows])
            Kj = gain(Pp, Hj, Rj)
            Yj = spd_inv(joseph(Pp, Kj, Hj, Rj))
            Yf = Yf + Yj
            Tacc = Tacc + Yj @ (eye - Kj @ Hj)
            U = U + _embed(Yj @ Kj, rows, m)
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
    """
    batch = present.shape[:-2]
    n, m = sys.n, sys.m
    S = len(sys.sensors)
    allrows = np.arange(m)
    locs = [
        _KF(sys, allrows[sl], s.R, batch)
        for s, sl in zip(sys.sensors, sys.sensor_slices, strict=True)
    ]
    s0 = np.concatenate([lk.s0 for lk in locs])
    twins = _twins(sys)
    if sys.prior is not None:
        J = _bc(np.kron(np.ones((S, S)), sys.prior.cov), batch + (S * n, S * n)).copy()
    else:
        J = np.zeros(batch + (S * n, S * n))
    # Only the generalised Millman formula and the average's honest covariance need the
    # cross-covariances of eq. (35).
    joint = name in ("MSC-GMF", "AVG")
    steps = []
    ci_pending: list[tuple[int, np.ndarray, np.ndarray]] = []
    steady = _Steady(present)
    K1 = present.shape[-2]
    for k in range(K1):
        first = k == 0
        sts = _step_locals(locs, present[..., k, :], first, twins)
        if joint:
            if not first:
                Phi = _block_diag([st.Phi for st in sts])
                Gam = np.concatenate([_bc(st.Gam, batch + (n, n)) for st in sts], axis=-2)
                J = Phi @ J @ mT(Phi) + Gam @ sys.GQG @ mT(Gam)
            Psi = _block_diag([st.Psi for st in sts])
            Lam = np.concatenate([_bc(st.Lam, batch + (n, m)) for st in sts], axis=-2)
            _, Rk = _masked(sys.H, sys.R, present[..., k, :])
            J = sym(Psi @ J @ mT(Psi) + Lam @ Rk @ mT(Lam))
        T = _block_diag([st.T for st in sts])
        U = np.concatenate([_bc(st.U, batch + (n, m)) for st in sts], axis=-2)
        all_cov = not any(lk.info for lk in locs)
        D = np.concatenate([_bc(st.D, batch + (n, n)) for st in sts], axis=-2)
        # A local's state s_j is D_j x + sigma_j with sigma_j = -g_j (mean form: s = x_hat,
        # g = x - x_hat) or +g_j (information form: s = y, g = y - Y x); J is cov(g).
        sign = _signs(tuple(lk.info for lk in locs), n)
        if name == "MSC":
            O, P = _msc_readout(locs, sts, batch, n)
        elif name == "MSC-GMF":
            # Eqs. (2)-(7) with the unbiasedness constraint sum_j c_j D_j = I, which is eq. (7)
            # when every local is in mean form (D_j = I) and extends it to information form.
            if all_cov:
                ws, P = gmf_weights(J, n)  # sign = -I cancels
            else:
                ws, P = gmf_weights(sign @ J @ sign, n, D)
            O = np.concatenate(ws, axis=-1)
        elif name == "AVG":
            # Equal weights on the local means (eq. 2, c_i = I/S) and the covariance they
            # really give, eq. (4); undefined (NaN) while a local has no mean yet.
            Rs = [_mean_readout(lk, st, batch, n) for lk, st in zip(locs, sts, strict=True)]
            O = np.concatenate(Rs, axis=-1) / S
            Msig = O @ sign
            P = sym(Msig @ J @ mT(Msig))
        else:  # CI: the omegas of all steps are solved together after the loop
            O = P = None
            Ys, Ws = _local_infos(locs, sts, batch, n)
            ci_pending.append((len(steps), np.stack(Ys, axis=-3), np.stack(Ws, axis=-3)))
        steps.append(StepMap(T, U, O, P, D))
        if all_cov and steady.reached(*([J] if joint else [lk.mat for lk in locs])):
            _fill(steps, K1)
            break
    info = {"omega": _ci_readouts(steps, ci_pending, batch, criterion)} if name == "CI" else {}
    D0 = np.concatenate([lk.D0 for lk in locs])
    return Plan(name, s0, steps, per_run=bool(batch), info=info, D0=D0)


@lru_cache(maxsize=64)
def _signs(info: tuple[bool, ...], n: int) -> np.ndarray:
    """diag(+I for a local in information form, -I in mean form): sigma = sign g."""
    return np.kron(np.diag([1.0 if i else -1.0 for i in info]), np.eye(n))


def _twins(sys: System) -> list[int]:
    """For each sensor, the first sensor with the same H and R (itself if none): their local
    filters run the same covariance recursion, so it is computed once per step."""
    first: dict[bytes, int] = {}
    out = []
    for j, sen in enumerate(sys.sensors):
        key = sen.H.tobytes() + b"|" + sen.R.tobytes() + repr(sen.H.shape).encode()
        out.append(first.setdefault(key, j))
    return out


def _step_locals(
    locs: list[_KF], present: np.ndarray, first: bool, twins: list[int]
) -> list[_Step]:
    """One step of every local filter; a twin with the same measurement pattern this step
    takes its original's gains and covariances, re-embedded at its own rows."""
    sts: list[_Step] = []
    for j, lk in enumerate(locs):
        o = twins[j]
        if o != j and np.array_equal(present[..., lk.rows], present[..., locs[o].rows]):
            src, st = locs[o], sts[o]
            lk.info, lk.mat = src.info, src.mat

            def move(A: np.ndarray, src: _KF = src, lk: _KF = lk) -> np.ndarray:
                return _embed(A[..., src.rows], lk.rows, lk.m)

            sts.append(
                _Step(st.T, move(st.U), st.O, st.P, st.Phi, st.Gam, st.Psi, move(st.Lam), st.D)
            )
        else:
            sts.append(lk.step(present[..., lk.rows], first))
    return sts


def _ci_readouts(
    steps: list[StepMap],
    pending: list[tuple[int, np.ndarray, np.ndarray]],
    batch: tuple[int, ...],
    criterion: str,
) -> np.ndarray:
    """Covariance intersection of the local estimates at the steps in `pending` (step index,
    local informations Y_j and maps W_j with Y_j x_j = W_j s_j, batch + (S, n, n)): every step's
    (and run's) omega in one `ci_omegas` call, then P = (sum w_j Y_j)^-1 and the weights
    w_j P W_j written into those steps' maps. In information form a local with too little
    information to have a mean of its own still contributes. Returns the omegas, batch +
    (K+1, S)."""
    K1 = len(steps)
    Y0 = pending[0][1]
    S, n = Y0.shape[-3], Y0.shape[-1]
    Ys = np.stack([y for _, y, _ in pending])  # (L,) + batch + (S, n, n)
    Ws = np.stack([w for _, _, w in pending])
    om = ci_omegas(Ys.reshape((-1, S, n, n)), criterion).reshape(Ys.shape[:-2])
    P = inv_or_nan(np.einsum("...j,...jab->...ab", om, Ys))
    O = np.concatenate([om[..., j, None, None] * (P @ Ws[..., j, :, :]) for j in range(S)], -1)
    by_id = {}
    for i, (k, _, _) in enumerate(pending):
        steps[k].O, steps[k].P = O[i], P[i]
        by_id[id(steps[k])] = om[i]
    omega = np.full((K1,) + batch + (S,), np.nan)
    for k, st in enumerate(steps):
        if id(st) in by_id:
            omega[k] = by_id[id(st)]
    return np.moveaxis(omega, 0, -2)


def _local_infos(
    locs: list[_KF], sts: list[_Step], batch: tuple[int, ...], n: int
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each local's information matrix Y_j and the map W_j with Y_j x_j = W_j s_j (the
    information vector is the state itself while a local is in information form)."""
    Ys, Ws = [], []
    for lk, st in zip(locs, sts, strict=True):
        if lk.info:
            Ys.append(lk.mat)
            Ws.append(_bc(np.eye(n), batch + (n, n)))
        else:
            Y = spd_inv(st.P)
            Ys.append(Y)
            Ws.append(Y)
    return Ys, Ws


def _mean_readout(lk: _KF, st: _Step, batch: tuple[int, ...], n: int) -> np.ndarray:
    """x_j = R_j s_j: I in mean form, Y_j^-1 in information form (NaN where singular)."""
    if not lk.info:
        return _bc(np.eye(n), batch + (n, n))
    return inv_or_nan(lk.mat)


def _msc_readout(
    locs: list[_KF], sts: list[_Step], batch: tuple[int, ...], n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Millman fusion (33)-(34) in information form: P^-1 = sum Y_j, x = P sum Y_j x_j, where
    Y_j x_j is the information vector itself for a local still in information form."""
    Ys, Ws = _local_infos(locs, sts, batch, n)
    P = inv_or_nan(sum(Ys))
    return np.concatenate([P @ W for W in Ws], axis=-1), P


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
    for k in range(K1 - 1, -1, -1):
        if steady.enabled and k < K1 - 3 and Smat[k + 1] is Smat[k + 2]:
            V[k], L[k], Smat[k] = V[k + 1], L[k + 1], Smat[k + 1]
            continue
        Hk, Rk = _masked(sys.H, sys.R, present[..., k, :])
        RiH = np.linalg.solve(Rk, Hk)
        V[k] = mT(RiH)
        if k < K1 - 1:
            Hn = _masked(sys.H, sys.R, present[..., k + 1, :])[0]
            Splus = sym(Smat[k + 1] + mT(Hn) @ mT(V[k + 1]))
            Bm = eye + Splus @ sys.GQG
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
