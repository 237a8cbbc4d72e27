"""The fusion architectures (DESIGN.md, "Architectures") with EKF or UKF local filters, batched
over runs: every run has its own linearisation, so each step is a handful of stacked operations
on (M, n) means and (M, n, n) covariances, never a loop over runs.

* CKF      one filter on all sensors, one stacked update per instant with every sensor that
           measures then (eq. 30 with h stacked, one linearisation);
* SKF      one filter on one sensor (`SKF:<sensor>`, the first by default);
* HKF      eqs. (36)-(40): each local filter updates the fused prediction with its own sensor,
           the centre adds their equivalent measurements Y_j x_j - Y_pred x_pred;
* per-sensor architectures (MSC, MSC-GMF, CI, AVG, any registered rule): local filters, one
           per sensor, fused by the architecture's rule (`architectures.definition.Rule`); a
           rule that reads the joint error covariance gets it carried as in eq. (35) through
           the *linearised* gains: J_ij <- F_i J_ij F_j^T + Q, J_ij <- (I - K_i H_i) J_ij
           (I - K_j H_j)^T (i != j; the sensors' noises are independent), each diagonal block
           the local's own covariance;
* FBS      the extended / unscented Rauch-Tung-Striebel smoother on the CKF (for linear models
           the forward-backward Millman fusion of eqs. 25-28 computes the same estimate):
           G_k = C_{k+1} P-_{k+1}^-1, x_s = x_k + G (x_s' - x-_{k+1}),
           P_s = P_k + G (P_s' - P-_{k+1}) G^T, C the cross-covariance of the prediction
           (P F^T for the EKF; of the sigma points, Sarkka 2008, for the UKF).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ...errors import FusionlogError, NumericalError
from ..architectures.definition import Architecture
from ..architectures.registry import definition, parse_arch
from ..kernels import lanes
from ..linalg import NUMERICAL_FAILURES, mT, spd_inv, sym
from ..model import System
from ..models.polar import PolarSensor
from .local import Stacked, predict, transition, ukf_params, update


@dataclass
class Track:
    """Estimates of M runs: mean (M, K+1, n) and each run's covariance (M, K+1, n, n)."""

    mean: np.ndarray
    cov: np.ndarray


#: An architecture's estimates, one instant at a time: (mean (M, n), covariances (M, n, n)).
Steps = Iterator[tuple[np.ndarray, np.ndarray]]


class _Out:
    """The estimates as they are made: the means (M, K+1, n), and the covariances on lanes
    (K+1, n, n, M), so that storing a step's (which the filters keep on lanes) is one copy;
    the track sees them as (M, K+1, n, n)."""

    def __init__(self, M: int, K1: int, n: int) -> None:
        self.mean = np.empty((M, K1, n))
        self._cov = np.empty((K1, n, n, M))

    def put(self, k: int, x: np.ndarray, P: np.ndarray) -> None:
        self.mean[:, k] = x
        self._cov[k] = lanes(P)

    def track(self) -> Track:
        return Track(self.mean, np.moveaxis(self._cov, -1, 0))


class _Steps:
    """What every architecture needs of the instants: the intervals, the stacked measurement
    columns of each sensor, and which sensors measure at an instant in some run."""

    def __init__(
        self,
        system: System,
        z: np.ndarray,
        times: np.ndarray | None,
        off: int,
        instants: int | None = None,
    ):
        if times is not None:
            system = system.on_times(np.asarray(times, dtype=float))
        self.system, self.off = system, off
        #: runs and instants; `instants`: of a log whose readings z come in blocks (`feed`)
        self.M, self.K1 = z.shape[0], z.shape[1] if instants is None else instants
        # the instants, for messages only: a system already on its instants knows its intervals
        self.times = _instants(system, self.K1) if times is None else np.asarray(times, float)
        m = self.system.m
        self.cols = [np.arange(m)[sl] for sl in self.system.sensor_slices]
        self.ukf = ukf_params(self.system)
        self.work: dict = {}  # the EKF update's temporaries, reused from instant to instant
        self.feed(0, z)

    def feed(self, k0: int, z: np.ndarray) -> None:
        """The readings z (M, w, m) of the instants k0..k0+w-1 (a long log's block of time,
        `core.nonlinear.long_log`; else all of them, k0 = 0), and which sensors measure then."""
        self.z, self.k0 = z, k0
        some = (~np.isnan(z)).any(axis=0)  # (w, m): the column has a reading in some run
        self.measures = np.stack([some[:, c].any(axis=1) for c in self.cols], axis=1)  # (w, S)

    def predict(self, k: int, x: np.ndarray, P: np.ndarray):
        return predict(*transition(self.system, k), x, P, self.ukf)

    def update(self, k: int, which: list[int], x: np.ndarray, P: np.ndarray):
        """The update at instant k with the sensors `which` that measure then (None: none)."""
        which = [j for j in which if self.measures[k - self.k0, j]]
        if not which:
            return None
        model = Stacked(tuple(self.system.sensors[j] for j in which))
        zk = self.z[:, k - self.k0, np.concatenate([self.cols[j] for j in which])]
        self._check_ranges(k, which, x, zk)
        return update(model, x, P, zk, self.ukf, self.work)

    def _check_ranges(self, k: int, which: list[int], x: np.ndarray, zk: np.ndarray) -> None:
        """A range or bearing has no derivative at the sensor's own position: refuse it."""
        start = 0
        for j in which:
            s = self.system.sensors[j]
            if isinstance(s, PolarSensor) and not (away := s.ranges(x) > 0).all():
                present = ~np.isnan(zk[:, start : start + s.dim]).any(axis=-1)
                bad = present & ~away  # NaN ranges too
                if bad.any():
                    run = self.off + int(np.argmax(bad))
                    raise NumericalError(
                        f"sensor {s.name!r}: the estimate is at the sensor's position (range 0) "
                        f"in run {run}, instant {k} (t = {self.times[k]:g} s): its bearing and "
                        "Jacobian are undefined there; move the sensor or the prior mean"
                    )
            start += s.dim

    def start(self) -> tuple[np.ndarray, np.ndarray]:
        pr = self.system.prior
        return np.tile(pr.mean, (self.M, 1)), np.tile(pr.cov, (self.M, 1, 1))


def _instants(system: System, K1: int) -> np.ndarray:
    """The instants of a system on its instants: k dt, or the sums of its intervals."""
    if system.intervals is not None:
        return np.concatenate([[0.0], np.cumsum(system.intervals)])
    return np.arange(K1) * system.dt


def estimate(
    system: System, arch: str, z: np.ndarray, times: np.ndarray | None, run_offset: int = 0
) -> Track:
    """Estimates of every run (z: (M, K+1, m), NaN = absent) with architecture `arch` on the
    instants `times` (K+1,) s (None: `system` is already on its instants, `System.on_times`);
    `run_offset` (the block's first run) only names runs in errors."""
    M, K1 = z.shape[:2]
    out = _Out(M, K1, system.n)
    for k, (x, P) in enumerate(estimate_steps(system, arch, z, times, run_offset)):
        out.put(k, x, P)
    return out.track()


def estimate_steps(
    system: System, arch: str, z: np.ndarray, times: np.ndarray | None, run_offset: int = 0
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """`estimate` one instant at a time: (mean (M, n), covariances (M, n, n)) for k = 0..K,
    each computed when asked for (the filters keep one instant in memory, not all; FBS, a
    smoother, all of them)."""
    require_filter(system, arch)
    return steps_of(_Steps(system, z, times, run_offset), arch)


def require_filter(system: System, arch: str) -> None:
    """An architecture name no definition has: ValueError; a nonlinear model without a local
    filter: FusionlogError."""
    definition(parse_arch(arch, [s.name for s in system.sensors])[0])
    if system.filter is None and not system.linear:
        raise FusionlogError(
            'the model is nonlinear and has no local filter: give [estimate] filter = "EKF" or '
            '"UKF", or --filter'
        )


def steps_of(st: _Steps, arch: str) -> Steps:
    """`estimate_steps` of the instants of `st` (whose readings may come in blocks)."""
    names = [s.name for s in st.system.sensors]
    base, sensor = parse_arch(arch, names)
    kind = definition(base)
    if kind.locals == "centralised":
        return _named(_filter(st, list(range(len(names)))), arch)
    if kind.locals == "single":
        return _named(_filter(st, [names.index(sensor)]), arch)
    if kind.locals == "smoother":
        return _named(_smoother(st, arch), arch)
    if kind.locals == "hierarchical":
        return _named(_hkf(st), arch)
    return _named(_track_to_track(st, kind), arch)


def _named(steps: Steps, arch: str) -> Steps:
    """`steps` with their numerical failures as one NumericalError naming the architecture
    and the step (what the linear plans' errors name), and an estimate that overflows refused:
    a NaN mean would be read downstream as "no estimate". The smoother's failures name the
    step of its forward pass (its backward pass runs before its first step is given)."""
    for k in range(np.iinfo(np.int64).max):
        where = f"architecture {arch}, step {k}"
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                x, P = next(steps)
        except StopIteration:
            return
        except NumericalError as e:
            if str(e).startswith("architecture "):  # named already (the smoother's filter)
                raise
            raise NumericalError(f"{where}: {e}") from None
        except NUMERICAL_FAILURES as e:
            raise NumericalError(
                f"{where}: a matrix is singular or overflows to working precision "
                f"({type(e).__name__}: {e})"
            ) from e
        if not (np.isfinite(x).all() and np.isfinite(P).all()):
            raise NumericalError(f"{where}: the estimate overflows (not finite)")
        yield x, P


def _filter(
    st: _Steps, which: list[int], keep: list | None = None, first: int = 0, state=None
) -> Steps:
    """One filter on the sensors `which`; with `keep`, each step's (x-, P-, C) is appended.
    From instant `first` on, `state` the estimate (x, P) of the instant before (None: the
    prior at instant 0)."""
    x, P = st.start() if state is None else state
    for k in range(first, st.K1):
        if k:
            x, P, _, C = st.predict(k, x, P)
            if keep is not None:
                keep.append((x, P, C))
        u = st.update(k, which, x, P)
        if u is not None:
            x, P = u.x, u.P
        yield x, P


def _smoother(st: _Steps, arch: str) -> Steps:
    """The extended / unscented RTS smoother on the CKF (module docstring)."""
    keep: list = []
    M, K1 = st.z.shape[:2]
    out = _Out(M, K1, st.system.n)
    forward = _named(_filter(st, list(range(len(st.system.sensors))), keep), arch)
    for k, (x, P) in enumerate(forward):
        out.put(k, x, P)
    tr = out.track()
    rts(tr.mean, tr.cov, keep)
    for k in range(K1):
        yield tr.mean[:, k], tr.cov[:, k]


def rts(mean: np.ndarray, cov: np.ndarray, keep: list) -> None:
    """The RTS backward pass in place over instants j = w-2..0 of the forward estimates mean
    (M, w, n), cov (M, w, n, n), whose last instant is smoothed already; keep[j] the
    prediction (x-, P-, C) from instant j to j + 1 (module docstring)."""
    for k in range(mean.shape[1] - 2, -1, -1):
        xp, Pp, C = keep[k]  # the prediction from k to k + 1
        G = mT(np.linalg.solve(Pp, mT(C)))
        mean[:, k] += np.einsum("mij,mj->mi", G, mean[:, k + 1] - xp)
        cov[:, k] = sym(cov[:, k] + G @ (cov[:, k + 1] - Pp) @ mT(G))


def _hkf(st: _Steps) -> Steps:
    """Eqs. (36)-(40) with EKF/UKF locals restarting from the fused prediction."""
    x, P = st.start()
    for k in range(st.K1):
        if k:
            x, P, _, _ = st.predict(k, x, P)
        Yp = spd_inv(P, "the predicted covariance")
        Y, y = Yp.copy(), np.einsum("mij,mj->mi", Yp, x)
        yp = y.copy()
        for j in range(len(st.system.sensors)):
            u = st.update(k, [j], x, P)
            if u is None:
                continue
            Yj = spd_inv(u.P, "a local covariance")
            Y += Yj - Yp
            y += np.einsum("mij,mj->mi", Yj, u.x) - yp
        P = spd_inv(Y, "the fused information")
        x = np.einsum("mij,mj->mi", P, y)
        yield x, P


def _track_to_track(st: _Steps, arch: Architecture) -> Steps:
    """One local filter per sensor, fused at every instant by the architecture's rule."""
    M, K1 = st.M, st.K1
    n, S = st.system.n, len(st.system.sensors)
    joint = arch.joint
    x0, P0 = st.start()
    xs, Ps = [x0] * S, [P0] * S
    J = np.broadcast_to(P0[:, None, None], (M, S, S, n, n)).copy() if joint else None
    eye = np.eye(n)
    for k in range(K1):
        if k:
            pred = [st.predict(k, xs[i], Ps[i]) for i in range(S)]
            xs, Ps = [p[0] for p in pred], [p[1] for p in pred]
            if joint:
                Fs = np.stack([np.broadcast_to(p[2], (M, n, n)) for p in pred], axis=1)
                motion, dt = transition(st.system, k)
                Q = motion.Q(dt)
                J = _congruence(Fs, J) + Q
        A = np.broadcast_to(eye, (M, S, n, n)).copy()
        for i in range(S):
            u = st.update(k, [i], xs[i], Ps[i])
            if u is not None:
                xs[i], Ps[i] = u.x, u.P
                A[:, i] -= u.K @ u.H
        if joint:
            J = _congruence(A, J)
            for i in range(S):
                J[:, i, i] = Ps[i]  # the local's own covariance (equal for the EKF)
        yield _fuse(arch, np.stack(xs, 1), np.stack(Ps, 1), J, st.system.ci_criterion)


def _congruence(T: np.ndarray, J: np.ndarray) -> np.ndarray:
    """J_ij <- T_i J_ij T_j^T for every block of the joint covariance J (M, S, S, n, n), with
    T (M, S, n, n): two stacked products (a three-operand einsum would loop in Python's
    order over the small axes)."""
    return (T[:, :, None] @ J) @ mT(T)[:, None]


def _fuse(
    arch: Architecture, xs: np.ndarray, Ps: np.ndarray, J: np.ndarray | None, criterion: str
) -> tuple[np.ndarray, np.ndarray]:
    """The rule of `arch` (`definition.Rule`) on the locals' means xs (M, S, n), covariances
    Ps (M, S, n, n) and joint error covariance J (M, S, S, n, n) (None: the rule reads none):
    x = C [x_1; ...; x_S]."""
    M, S, n = xs.shape
    joint = None if J is None else sym(J.transpose(0, 1, 3, 2, 4).reshape(M, S * n, S * n))
    C, P = arch.rule(Ps, joint, criterion)
    return np.einsum("mij,mj->mi", C, xs.reshape(M, S * n)), P
