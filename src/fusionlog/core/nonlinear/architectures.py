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
from ..kernels import all_finite, lanes
from ..late_policy import ekf_retrodict_refusal, is_late, late_refusal
from ..linalg import NUMERICAL_FAILURES, mT, spd_inv, sym
from ..model import System
from ..models.polar import PolarSensor
from .late import arrival_instants, late_steps
from .local import Stacked, predict, stacked, transition, ukf_params, update


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

    def __init__(self, system: System, z: np.ndarray, times: np.ndarray | None, off: int):
        if times is not None:
            system = system.on_times(np.asarray(times, dtype=float))
        self.system, self.z, self.off = system, z, off
        # the instants, for messages only: a system already on its instants knows its intervals
        self.times = _instants(system, z.shape[1]) if times is None else np.asarray(times, float)
        m = self.system.m
        self.slices = self.system.sensor_slices
        self.cols = [np.arange(m)[sl] for sl in self.slices]
        some = (~np.isnan(z)).any(axis=0)  # (K+1, m): the column has a reading in some run
        self.measures = np.stack([some[:, c].any(axis=1) for c in self.cols], axis=1)  # (K+1, S)
        self.ukf = ukf_params(self.system)
        self.work: dict = {}  # the EKF update's temporaries, reused from instant to instant
        # what every instant would make again of a steady model: its transition (one F, Q),
        # and each group of sensors' stacked model and columns (one R)
        sy = self.system
        steady = sy.Fs is None and sy.Qs is None and sy.intervals is None
        self.motion = transition(self.system, 1) if steady else None
        self.models: dict | None = {} if self.system.Rs is None else None

    def transition(self, k: int):
        """`local.transition` from instant k-1 to k."""
        return self.motion or transition(self.system, k)

    def predict(self, k: int, x: np.ndarray, P: np.ndarray):
        return predict(*self.transition(k), x, P, self.ukf)

    def update(
        self,
        k: int,
        which: list[int],
        x: np.ndarray,
        P: np.ndarray,
        zk: np.ndarray | None = None,
    ):
        """The update at instant k with the sensors `which` that measure then (None: none);
        `zk` (M, m): the readings of instant k to use (default all of z's: late measurements
        give only those that have arrived, `late`)."""
        if zk is None:
            zk = self.z[:, k]
            which = [j for j in which if self.measures[k, j]]
        else:  # a sensor measures if some run has one of its readings
            absent = np.isnan(zk).all(axis=0).tolist()
            which = [j for j in which if not all(absent[self.slices[j]])]
        if not which:
            return None
        model, cols = self._model(k, which)
        zk = zk[:, cols]
        if self.ukf is not None:  # the sigma points may straddle the sensor: asked first
            self._check_ranges(k, which, x, zk)
            return update(model, x, P, zk, self.ukf)
        # the EKF's Jacobian at a range 0 is 0/0: not finite, which asks why (not before: the
        # check costs as much as the update's products for one run)
        try:
            u = update(model, x, P, zk, None, self.work)
        except (NumericalError, *NUMERICAL_FAILURES):
            self._check_ranges(k, which, x, zk)
            raise
        if not (all_finite(u.x) and all_finite(u.P)):
            self._check_ranges(k, which, x, zk)
        return u

    def _model(self, k: int, which: list[int]) -> tuple[Stacked, np.ndarray | slice]:
        """The sensors `which` as one measurement at instant k, and their columns of z (a
        slice where they are adjacent: a view), made once per group where R is the same at
        every instant."""
        got = None if self.models is None else self.models.get(key := tuple(which))
        if got is None:
            cols = np.concatenate([self.cols[j] for j in which])
            if (np.diff(cols) == 1).all():
                cols = slice(int(cols[0]), int(cols[-1]) + 1)
            got = stacked(self.system, which, k), cols
            if self.models is not None:
                self.models[key] = got
        return got

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
        M = self.z.shape[0]
        pr = self.system.prior
        return np.tile(pr.mean, (M, 1)), np.tile(pr.cov, (M, 1, 1))


def _instants(system: System, K1: int) -> np.ndarray:
    """The instants of a system on its instants: k dt, or the sums of its intervals."""
    if system.intervals is not None:
        return np.concatenate([[0.0], np.cumsum(system.intervals)])
    return np.arange(K1) * system.dt


def estimate(system: System, arch: str, z: np.ndarray, times: np.ndarray | None, **kw) -> Track:
    """Estimates of every run (z: (M, K+1, m), NaN = absent) with architecture `arch` on the
    instants `times` (K+1,) s (None: `system` is already on its instants, `System.on_times`);
    `kw`: `estimate_steps`'s run_offset (the block's first run, which only names runs in
    errors) and, for late sensors, arrival (M, K+1, S) s, when each reading arrived (default:
    the sensors' fixed latencies), under the policy `system.late` (`late`)."""
    M, K1 = z.shape[:2]
    out = _Out(M, K1, system.n)
    for k, (x, P) in enumerate(estimate_steps(system, arch, z, times, **kw)):
        out.put(k, x, P)
    return out.track()


def estimate_steps(
    system: System,
    arch: str,
    z: np.ndarray,
    times: np.ndarray | None,
    run_offset: int = 0,
    arrival: np.ndarray | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """`estimate` one instant at a time: (mean (M, n), covariances (M, n, n)) for k = 0..K,
    each computed when asked for (the filters keep one instant in memory, not all; FBS, a
    smoother, all of them)."""
    kind = require_filter(system, arch)
    if is_late(system) and (why := late_refusal(system, kind.locals, arch)) is not None:
        raise FusionlogError(why)
    st = _Steps(system, z, times, run_offset)
    if kind.locals == "smoother":
        return _named(_smoother(st, arch), arch)
    m = machine_of(st, arch)
    if is_late(system):
        arrive = arrival_instants(st.system, st.times, arrival)
        return _named(late_steps(m, late_filters(m, arch), arrive), arch)
    return _named(_run(m), arch)


def late_filters(m: Machine, arch: str) -> list[list[int]]:
    """The sensors each filter of machine `m` (architecture `arch`) fuses: one local per
    sensor, or its one filter's (or centre's) sensors (neglect's last update is per filter)."""
    S = len(m.st.system.sensors)
    if require_filter(m.st.system, arch).locals == "per-sensor":
        return [[j] for j in range(S)]
    return [m.which] if isinstance(m, _Filter) else [list(range(S))]


def require_filter(system: System, arch: str) -> Architecture:
    """The definition of `arch` (a name no definition has: ValueError); a nonlinear model
    without a local filter: FusionlogError."""
    kind = definition(parse_arch(arch, [s.name for s in system.sensors])[0])
    if system.filter is None and not system.linear:
        raise FusionlogError(
            'the model is nonlinear and has no local filter: give [estimate] filter = "EKF" or '
            '"UKF", or --filter'
        )
    return kind


def machine_of(st: _Steps, arch: str) -> Machine:
    """The recursion (`Machine`) of `arch`, a filter (not the smoother) on the instants of
    `st`: what `estimate_steps` runs, and a long log carries from block to block
    (`core.nonlinear.long_log`)."""
    names = [s.name for s in st.system.sensors]
    base, sensor = parse_arch(arch, names)
    kind = definition(base)
    if kind.locals == "centralised":
        return _Filter(st, list(range(len(names))))
    if kind.locals == "single":
        return _Filter(st, [names.index(sensor)])
    if kind.locals == "hierarchical":
        return _Hkf(st)
    return _TrackToTrack(st, kind)


def _named(steps: Steps, arch: str) -> Steps:
    """`steps` with their numerical failures as one NumericalError naming the architecture
    and the step (what the linear plans' errors name), and an estimate that overflows refused:
    a NaN mean would be read downstream as "no estimate". The smoother's failures name the
    step of its forward pass (its backward pass runs before its first step is given)."""
    for k in range(np.iinfo(np.int64).max):
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                x, P = next(steps)
        except StopIteration:
            return
        except NumericalError as e:
            where = f"architecture {arch}, step {k}"
            if str(e).startswith("architecture "):  # named already (the smoother's filter)
                raise
            raise NumericalError(f"{where}: {e}") from None
        except NUMERICAL_FAILURES as e:
            where = f"architecture {arch}, step {k}"
            raise NumericalError(
                f"{where}: a matrix is singular or overflows to working precision "
                f"({type(e).__name__}: {e})"
            ) from e
        if not (all_finite(x) and all_finite(P)):
            raise NumericalError(
                f"architecture {arch}, step {k}: the estimate overflows (not finite)"
            )
        yield x, P


class Machine:
    """An architecture as a recursion on its state: s_k = step(k, s_{k-1}, z_k) (s_{-1} =
    `start()`: step 0 only updates), its estimate at k `out(s_k)`; z_k (M, m) the readings it
    may use at k (NaN: none). Late measurements rerun `step` from a stored state (`late`)."""

    def __init__(self, st: _Steps) -> None:
        self.st = st

    def start(self):
        return self.st.start()

    def step(self, k: int, s, zk: np.ndarray):
        raise NotImplementedError

    def out(self, s) -> tuple[np.ndarray, np.ndarray]:
        return s

    def retrodicting(self) -> list:
        """Its retrodicting filters (`retrodict.retrodict_steps`): [(sensors, in-order update
        or None for the stacked EKF update)]."""
        return [(self.which, None)]

    def combine(self, ests: tuple) -> tuple[np.ndarray, np.ndarray]:
        """The estimate of its retrodicting filters' estimates (x, P) at an instant."""
        return ests[0]


class _Filter(Machine):
    """One filter on the sensors `which`; with `keep`, each step's (x-, P-, C) is appended."""

    def __init__(self, st: _Steps, which: list[int], keep: list | None = None) -> None:
        super().__init__(st)
        self.which, self.keep = which, keep

    def step(self, k: int, s, zk: np.ndarray):
        x, P = s
        if k:
            x, P, _, C = self.st.predict(k, x, P)
            if self.keep is not None:
                self.keep.append((x, P, C))
        u = self.st.update(k, self.which, x, P, zk)
        if u is not None:
            x, P = u.x, u.P
        return x, P


def _run(m: Machine) -> Steps:
    """The machine on every reading as it is taken (no sensor late)."""
    s = m.start()
    for k in range(m.st.z.shape[1]):
        s = m.step(k, s, m.st.z[:, k])
        yield m.out(s)


def _filter_machine(st: _Steps, keep: list | None = None) -> Machine:
    """The CKF's recursion (FBS's forward filter); with `keep`, each step's (x-, P-, C)."""
    return _Filter(st, list(range(len(st.system.sensors))), keep)


def _filter(st: _Steps, which: list[int], keep: list | None = None) -> Steps:
    """One filter on the sensors `which`; with `keep`, each step's (x-, P-, C) is appended."""
    return _run(_Filter(st, which, keep))


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


class _Hkf(Machine):
    """Eqs. (36)-(40) with EKF/UKF locals restarting from the fused prediction. Retrodicting,
    its centre is one filter on every sensor with its own update (`retrodict` docstring)."""

    def __init__(self, st: _Steps) -> None:
        super().__init__(st)
        self.which = list(range(len(st.system.sensors)))

    def retrodicting(self) -> list:
        return [(self.which, self.fuse)]

    def step(self, k: int, s, zk: np.ndarray):
        st, (x, P) = self.st, s
        if k:
            x, P, _, _ = st.predict(k, x, P)
        return self.fuse(k, x, P, zk)

    def fuse(self, k: int, x: np.ndarray, P: np.ndarray, zk: np.ndarray):
        """The locals' updates of the prediction (x, P) with the readings zk of instant k,
        fused by the centre (eqs. 36-37)."""
        st = self.st
        Yp = spd_inv(P, "the predicted covariance")
        Y, y = Yp.copy(), np.einsum("mij,mj->mi", Yp, x)
        yp = y.copy()
        for j in range(len(st.system.sensors)):
            u = st.update(k, [j], x, P, zk)
            if u is None:
                continue
            Yj = spd_inv(u.P, "a local covariance")
            Y += Yj - Yp
            y += np.einsum("mij,mj->mi", Yj, u.x) - yp
        P = spd_inv(Y, "the fused information")
        return np.einsum("mij,mj->mi", P, y), P


class _TrackToTrack(Machine):
    """One local filter per sensor, fused at every instant by the architecture's rule; the
    state is the locals' means, covariances and (for a rule that reads it) joint covariance."""

    def __init__(self, st: _Steps, arch: Architecture) -> None:
        super().__init__(st)
        self.arch = arch

    def start(self):
        st = self.st
        M, n, S = st.z.shape[0], st.system.n, len(st.system.sensors)
        x0, P0 = st.start()
        J = np.broadcast_to(P0[:, None, None], (M, S, S, n, n)).copy() if self.arch.joint else None
        return [x0] * S, [P0] * S, J

    def step(self, k: int, s, zk: np.ndarray):
        st, joint = self.st, self.arch.joint
        xs, Ps, J = list(s[0]), list(s[1]), s[2]
        M, n, S = st.z.shape[0], st.system.n, len(xs)
        if k:
            pred = [st.predict(k, xs[i], Ps[i]) for i in range(S)]
            xs, Ps = [p[0] for p in pred], [p[1] for p in pred]
            if joint:
                Fs = np.stack([np.broadcast_to(p[2], (M, n, n)) for p in pred], axis=1)
                motion, dt = st.transition(k)
                J = _congruence(Fs, J) + motion.Q(dt)
        # I - K H of each local, for the joint covariance only (K and H are made when asked)
        A = np.broadcast_to(np.eye(n), (M, S, n, n)).copy() if joint else None
        for i in range(S):
            u = st.update(k, [i], xs[i], Ps[i], zk)
            if u is not None:
                xs[i], Ps[i] = u.x, u.P
                if joint:
                    A[:, i] -= u.K @ u.H
        if joint:
            J = _congruence(A, J)
            for i in range(S):
                J[:, i, i] = Ps[i]  # the local's own covariance (equal for the EKF)
        return xs, Ps, J

    def out(self, s) -> tuple[np.ndarray, np.ndarray]:
        xs, Ps, J = s
        return _fuse(self.arch, np.stack(xs, 1), np.stack(Ps, 1), J, self.st.system.ci_criterion)

    def retrodicting(self) -> list:
        """One retrodicting EKF per sensor; a rule that reads the joint covariance refused."""
        if (why := ekf_retrodict_refusal(self.arch.name, self.arch.joint)) is not None:
            raise FusionlogError(why)
        return [([j], None) for j in range(len(self.st.system.sensors))]

    def combine(self, ests: tuple) -> tuple[np.ndarray, np.ndarray]:
        xs, Ps = np.stack([e[0] for e in ests], 1), np.stack([e[1] for e in ests], 1)
        return _fuse(self.arch, xs, Ps, None, self.st.system.ci_criterion)


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
