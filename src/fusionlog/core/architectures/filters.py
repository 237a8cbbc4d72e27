"""Kalman filters as per-step linear maps: the machinery every architecture is built from.

A filter (or a stack of S local filters, one per sensor) runs eqs. (14)-(18) with the Joseph
form (18), on the components of the stacked measurement z_k of eq. (30) it uses. Each step gives
the filter's map s_k = T s_{k-1} + U z_k, x_hat = O s_k and its covariance P, together with the
propagation of its error (for the joint covariance of eq. (35)). Without a prior a filter runs
in information form from zero information, exactly, until its information matrix is invertible.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, fields
from operator import sub

import numpy as np

from ...errors import NumericalError
from ..kalman import gain, joseph
from ..linalg import (
    all_finite,
    bc,
    buffer,
    inv_or_nan,
    is_invertible,
    lanes_copy,
    lanes_of,
    many_matrices,
    mm,
    mT,
    require_finite,
    solve,
    spd_inv,
    sym,
    take_runs,
    unlanes,
)
from ..model import System


def masked(H: np.ndarray, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H and R with absent rows made information-free: the row of H is zeroed and the absent
    component decoupled with unit variance, so its gain column is exactly zero.

    Per run (a large batch, for the batch kernels) the absent component keeps its own variance
    R_ii instead of 1: decoupled either way, it does not change any other number of the
    update (the Cholesky factor of a decoupled component does not touch the others), and with
    uncorrelated components R stays one matrix shared by all runs.
    """
    if p.shape == H.shape[:-1] and p.all():  # nothing absent, and no per-run pattern
        return H, R
    if p.ndim > H.ndim - 1 and many_matrices(p.shape[:-1]):  # per run: lanes for the kernels
        nb = p.ndim - 1
        pf = buffer((p.shape[-1],), p.shape[:-1])  # (r,) + batch, runs contiguous
        pf[...] = np.moveaxis(p, -1, 0)
        Hm = unlanes(lanes_of(H, nb) * pf[:, None])
        r = R.shape[-1]
        if not (R * (1.0 - np.eye(r))).any():  # uncorrelated components
            return Hm, R
        keep = pf[:, None] * pf[None, :]  # R_ij where both are present, and every R_ii
        keep[np.arange(r), np.arange(r)] = 1.0
        return Hm, unlanes(lanes_of(R, nb) * keep)
    pf = p.astype(float)
    Hm = H * pf[..., :, None]
    Rm = R * (pf[..., :, None] * pf[..., None, :]) + np.eye(R.shape[-1]) * (1.0 - pf)[..., None, :]
    return Hm, Rm


#: (pattern, R) pairs whose masked H and R a `Rows` keeps at most.
_MASKS_KEPT = 4096


@dataclass
class Rows:
    """The measurement components a filter uses: its H and R, and where they sit in the stacked
    measurement z_k of eq. (30).

    A stack of S local filters, one per sensor, carries a leading axis S, padded to the largest
    sensor dimension with components that carry no information: a zero row of H with unit,
    uncorrelated variance, which is what `masked` makes of an absent component. Their gain
    columns are exactly zero and masking leaves them as they are (so their `cols` entry is an
    arbitrary 0), and one batched computation serves sensors of different sizes.
    """

    H: np.ndarray  # ([S,] r, n)
    R: np.ndarray  # ([S,] r, r)
    cols: np.ndarray  # ([S,] r): index of each component in z_k
    E: np.ndarray  # ([S,] r, m): 0/1 placement, K E puts the columns of a gain K at its rows
    masks: dict[bytes, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)
    #: R at every instant, (K+1,) + R's shape, where it varies (a recorded log: System.Rs).
    Rs: np.ndarray | None = None

    @classmethod
    def of(
        cls, system: System, rows: np.ndarray, R: np.ndarray, Rs: np.ndarray | None = None
    ) -> Rows:
        """One filter on the components `rows` of z_k, believing noise covariance R (at every
        instant, or Rs[k] at instant k)."""
        return cls(system.linear_measurement()[rows], R, rows, np.eye(system.m)[rows], Rs=Rs)

    @classmethod
    def all_of(cls, system: System) -> Rows:
        """One filter on every component of z_k with the system's R of eq. (31)."""
        return cls.of(system, np.arange(system.m), system.R, system.Rs)

    @classmethod
    def per_sensor(cls, system: System) -> Rows:
        """A stack of one filter per sensor j, each with its own H_j and R_j."""
        S, m = len(system.sensors), system.m
        r = max(sen.dim for sen in system.sensors)
        H = np.zeros((S, r, system.n))
        R = np.tile(np.eye(r), (S, 1, 1))
        cols = np.zeros((S, r), dtype=int)
        E = np.zeros((S, r, m))
        Rs = None if system.Rs is None else np.tile(np.eye(r), (len(system.Rs), S, 1, 1))
        H_all, R_all = system.linear_measurement(), system.R  # asked of the sensor models
        for j, (sen, sl) in enumerate(zip(system.sensors, system.sensor_slices, strict=True)):
            d = sen.dim
            H[j, :d], R[j, :d, :d] = H_all[sl], R_all[sl, sl]
            if Rs is not None:
                Rs[:, j, :d, :d] = system.Rs[:, sl, sl]
            cols[j, :d] = np.arange(m)[sl]
            E[j, np.arange(d), cols[j, :d]] = 1.0
        return cls(H, R, cols, E, Rs=Rs)

    def masked(self, present: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`masked` H and R (at instant k where R varies) for the present components of z_k
        (`present`, batch + (m,)). A pattern shared by all runs usually recurs every step:
        its matrices are kept (when R is the same at every instant)."""
        R = self.R if self.Rs is None else self.Rs[k]
        if present.ndim > 1:
            return masked(self.H, R, present[..., self.cols])
        # A recorded log's R varies per message, but its instants repeat few (pattern, R)
        # pairs (a sensor's constant R, a localiser's R between its messages): kept by both.
        key = present.tobytes() if self.Rs is None else present.tobytes() + R.tobytes()
        got = self.masks.get(key)
        if got is None:
            if len(self.masks) >= _MASKS_KEPT:
                self.masks.clear()  # a log whose every R differs: bounded, not a leak
            got = self.masks[key] = masked(self.H, R, present[self.cols])
        return got


@dataclass
class FilterStep:
    """One step of a filter (or a stack): its map and the propagation of its error."""

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


def merge_steps(parts: list[tuple[np.ndarray, FilterStep]], shape: tuple[int, ...]) -> FilterStep:
    """The step of a stack of filters (batch + (S,) = `shape`) from the steps of parts of it,
    given as (indices of the local filters, their step)."""
    out = {}
    for f in fields(FilterStep):
        first = getattr(parts[0][1], f.name)
        arr = np.empty(shape + first.shape[-2:])
        for j, st in parts:
            arr[..., j, :, :] = getattr(st, f.name)
        out[f.name] = arr
    return FilterStep(**out)


@dataclass
class Part:
    """What a step of some filters needs: their matrices (covariance, or information matrix in
    information form), H and R this step (`masked`), placement E (see `Rows`), and their
    identity and zero maps, shaped once rather than broadcast at every step. For a stack the
    local axis is the third-last of every array."""

    mat: np.ndarray
    H: np.ndarray
    R: np.ndarray
    E: np.ndarray
    I: np.ndarray  # noqa: E741
    Z: np.ndarray

    def take(self, j: np.ndarray) -> Part:
        """The local filters j of a stack."""
        mats = (self.mat, self.H, self.R, self.E, self.I, self.Z)
        return Part(*(a[..., j, :, :] for a in mats))


class KalmanStack:
    """Kalman filters on parts of the stacked measurement, eqs. (14)-(18), Joseph form: one
    filter, or a stack of S local filters (one per sensor, `Rows.per_sensor`) whose steps are
    computed together, as batched arrays batch + (S, ., .).

    Without a prior a filter runs in information form from zero information, exactly, and
    switches to covariance form at the first step where its information matrix is invertible
    for every run; in a stack, each local filter switches on its own.
    """

    def __init__(self, system: System, rows: Rows, batch: tuple[int, ...]):
        n = system.n
        self.system = system
        # The transition of the step being computed (`step` replaces them on irregular
        # instants); the same objects at every step otherwise, which callers test with `is`.
        self.F, self.GQG = system.F, system.GQG
        self.rows = rows
        self.eye = np.eye(n)
        local = rows.H.shape[:-2]  # (S,) for a stack, () for one filter
        self.n_local = len(local)
        self.I = bc(self.eye, local + (n, n))
        self.Z = bc(np.zeros((n, n)), local + (n, n))
        S = int(np.prod(local, dtype=int))
        shape = batch + local + (n, n)
        # `info` (a flag per filter: still in information form, no covariance yet) and `mat`
        # (see Part) are replaced at every step, never modified in place.
        per_run = many_matrices(batch + local)  # the kernels' lanes layout from the start
        if system.prior is not None:
            self.info = np.zeros(local, dtype=bool)
            cov = bc(system.prior.cov, shape)
            self.mat = lanes_copy(cov) if per_run else cov.copy()
            self.s0 = np.tile(np.asarray(system.prior.mean, float), S)
            self.D0 = np.tile(np.eye(n), (S, 1))
        else:
            self.info = np.ones(local, dtype=bool)
            self.mat = lanes_copy(bc(np.zeros((n, n)), shape)) if per_run else np.zeros(shape)
            self.s0 = np.zeros(S * n)
            self.D0 = np.zeros((S * n, n))
            if not abs(np.linalg.det(system.F)) >= 1e-300:  # also NaN
                raise NumericalError(
                    "F is singular: without a prior the filters start in information form and "
                    "predict through F^-1"
                )
            self.Finv = np.linalg.inv(system.F)
        self.any_info = bool(self.info.any())

    def step(self, present: np.ndarray, k: int, parent: np.ndarray | None = None) -> FilterStep:
        """Step k of every filter, with the components `present` (batch + (m,)) of z_k; on
        history nodes (`BuildRequest.parent`), each node continues its parent's filter."""
        if parent is not None:
            self.mat = take_runs(self.mat, parent)
        first = k == 0
        if not first and not self.system.time_invariant:
            self.F, self.GQG = self.system.F_at(k), self.system.GQG_at(k)
            if self.any_info:
                self.Finv = np.linalg.inv(self.F)
        Hk, Rk = self.rows.masked(present, k)
        part = Part(self.mat, Hk, Rk, self.rows.E, self.I, self.Z)
        if not self.any_info:  # the usual case: all in covariance form, and they stay so
            st, mat, _ = self.step_cov(part, first)
            if not all_finite(mat):
                self._overflow(mat, first)
            self.mat = mat
            return st
        if self.info.all():  # all in information form: one batched step
            st, mat, info = self.step_info(part, first)
            if not all_finite(mat):
                self._overflow(mat, first)
            self.mat, self.info, self.any_info = mat, info, bool(info.any())
            return st
        # Local filters in different forms (no prior, and one local could invert its
        # information earlier than another): each group in its own form, then put together.
        mat, info, parts = np.empty_like(self.mat), self.info.copy(), []
        for form in (False, True):
            j = np.flatnonzero(self.info == form)
            st, mat[..., j, :, :], info[j] = self.step_form(form, part.take(j), first)
            parts.append((j, st))
        if not all_finite(mat):
            self._overflow(mat, first)
        self.mat, self.info, self.any_info = mat, info, bool(info.any())
        return merge_steps(parts, mat.shape[:-2])

    def _overflow(self, mat: np.ndarray, first: bool) -> None:
        """Report the filters' new matrices `mat`, which overflowed: the predicted covariance
        F P F' + G Q G' when it is the culprit (the usual case), else the update."""
        if not first and not self.any_info:
            require_finite(
                mm(mm(self.F, self.mat), self.F.T) + self.GQG, "the predicted covariance"
            )
        require_finite(mat, "the filter's covariance (or information) matrix")

    def step_form(self, info: bool, part: Part, first: bool):
        """One step of filters all in information form (`info`) or all in covariance form:
        their step, their new matrices and their new forms."""
        return self.step_info(part, first) if info else self.step_cov(part, first)

    def step_cov(self, part: Part, first: bool) -> tuple[FilterStep, np.ndarray, np.ndarray]:
        """Prediction and Joseph-form update, eqs. (14)-(18)."""
        if first:
            Pp, Tp, Gam = part.mat, self.eye, part.Z
        else:
            Pp, Tp, Gam = sym(mm(mm(self.F, part.mat), self.F.T) + self.GQG), self.F, part.I
        K = gain(Pp, part.H, part.R)
        IKH = self.eye - mm(K, part.H)
        P = joseph(Pp, K, part.H, part.R, IKH)
        Ke = mm(K, part.E)  # exact: each column of K E is one column of K, or zero
        info = np.zeros(P.shape[P.ndim - 2 - self.n_local : -2], dtype=bool)
        return FilterStep(mm(IKH, Tp), Ke, part.I, P, Tp, Gam, IKH, -Ke, part.I), P, info

    def step_info(self, part: Part, first: bool) -> tuple[FilterStep, np.ndarray, np.ndarray]:
        """Prediction and update of the information Y and information vector y, and the
        switch to covariance form where Y has become invertible."""
        Y, Hk = part.mat, part.H
        if first:
            A, Yp, Gam = self.eye, Y, part.Z
        else:
            # Prediction in information form valid for singular Y (and singular Q):
            # with M = F^-T Y F^-1, Y^- = (I + M GQG)^-1 M and y^- = (I + M GQG)^-1 F^-T y.
            Mi = mm(mm(self.Finv.T, Y), self.Finv)
            Bm = self.eye + mm(Mi, self.GQG)
            A = solve(Bm, bc(self.Finv.T, Bm.shape))
            Yp = sym(solve(Bm, Mi))
            Gam = -mm(mm(A, Y), self.Finv)
        RiH = solve(part.R, Hk, hermitian=True)
        Y = sym(Yp + mm(mT(Hk), RiH))
        Ue = mm(mT(RiH), part.E)
        ok = is_invertible(Y)
        # A filter switches to covariance form when its Y is invertible in every run.
        switch = np.all(ok, axis=tuple(range(ok.ndim - self.n_local)))
        if switch.all():
            P = spd_inv(Y)
            PUe = mm(P, Ue)
            step = FilterStep(mm(P, A), PUe, part.I, P, A, Gam, -P, -PUe, part.I)
            return step, P, ~switch
        Pinv = inv_or_nan(Y)  # per filter, as alone
        step = FilterStep(A, Ue, Pinv, Pinv, A, Gam, bc(self.eye, Y.shape), Ue, Y)
        if not switch.any():
            return step, Y, ~switch
        # Some local filters of a stack switch now, the others later. For the former,
        # inv_or_nan gave spd_inv(Y), as above.
        P = Pinv
        PUe = mm(P, Ue)
        cov = FilterStep(mm(P, A), PUe, part.I, P, A, Gam, -P, -PUe, part.I)
        w = switch[:, None, None]
        step = FilterStep(
            *(np.where(w, getattr(cov, f.name), getattr(step, f.name)) for f in fields(FilterStep))
        )
        return step, np.where(w, P, Y), ~switch


#: Whether `Steady` also triggers once a shared mask stops changing (`constant_tail`).
_CONSTANT_TAIL: ContextVar[bool] = ContextVar("constant_tail", default=False)


@contextmanager
def constant_tail() -> Iterator[None]:
    """Plans built inside take the steady shortcut from the instant their shared mask stops
    changing (`Steady`): the late sensors' stacked model (`core.latency`), whose mask has only
    the arriving lags present and repeats past the latency window. Plans of sensors on time
    keep the rule that wants every measurement present, so their numbers stay bit for bit."""
    token = _CONSTANT_TAIL.set(True)
    try:
        yield
    finally:
        _CONSTANT_TAIL.reset(token)


class Steady:
    """Detects the steady state of a Riccati recursion so that long horizons reuse one map.

    With every measurement present and a time-invariant model (regular instants), once the
    covariance state after step k equals the one after step k-1 (to rounding, 1e-15 relative),
    every later step's map is the same as step k's: the plan repeats it instead of recomputing
    10^5 identical gains.

    The same holds when the mask shared by the runs is the same row at every instant from
    `tail` on (late sensors with fixed latencies: past the latency window the same lags arrive
    at every instant, `core.latency`; only inside `constant_tail`): step k >= tail with the
    covariance state of step k - 1 maps like every later step. The caller then says which
    step it asks about (`k`).
    """

    def __init__(self, present: np.ndarray, system: System):
        self.enabled = present.ndim == 2 and bool(present.all()) and system.time_invariant
        self.prev: np.ndarray | None = None
        self.tail = 0 if self.enabled else None
        tail_ok = _CONSTANT_TAIL.get() and present.ndim == 2 and system.time_invariant
        if not self.enabled and tail_ok:
            same = (present == present[-1]).all(-1)  # rows equal to the last one
            tail = len(same) - int(np.argmin(same[::-1])) if not same.all() else 0
            self.tail = tail if tail < len(same) - 2 else None

    def reached(self, *mats: np.ndarray, k: int | None = None) -> bool:
        if not self.enabled and (self.tail is None or k is None):
            return False
        cur = mats[0].ravel() if len(mats) == 1 else np.concatenate([m.ravel() for m in mats])
        prev, self.prev = self.prev, cur
        if prev is None or (k is not None and k < self.tail):
            return False
        if cur.size <= 16:
            # A step's few numbers compare faster in Python than through numpy's calls, with
            # the same IEEE operations: the same decision to the last bit.
            c = cur.tolist()
            return max(map(abs, map(sub, c, prev.tolist()))) <= 1e-15 * max(map(abs, c))
        return bool(np.abs(cur - prev).max() <= 1e-15 * np.abs(cur).max())


def wide_range(system: System, spread: float = 1e8) -> bool:
    """Whether the model's noise and prior variances (diagonals of R, G Q G', P0) span more than
    `spread`: then covariances and informations are badly scaled and plain LU inverses lose
    accuracy (see `linalg.spd_inv_scaled`)."""
    mats = [system.R, system.GQG] + ([system.prior.cov] if system.prior is not None else [])
    d = np.concatenate([np.diagonal(m) for m in mats])
    d = d[d > 0]
    return bool(d.size) and float(d.max()) > spread * float(d.min())


def fill(steps: list, total: int) -> None:
    """Repeat the last (steady-state) element until the list has `total` entries."""
    steps.extend([steps[-1]] * (total - len(steps)))
