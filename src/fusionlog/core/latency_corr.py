"""Correlated sensors whose readings of one instant arrive apart (see `core.latency`).

Sensors i and j with E[v_i v_j'] = R_ij != 0 read instant t at once, but the reading of j
may arrive after that of i has been fused. Reprocessing is the Kalman estimate from exactly
the arrived readings, and those of one instant are jointly Gaussian with the joint R: fusing
z_j later as if independent of z_i would be wrong. The exact construction is the sequential
decorrelation of the readings of instant t in arrival order (Gram-Schmidt on the noises, as
in the sequential processing of correlated measurements, Bar-Shalom, Li, Kirubarajan 2001,
sec. 3.4; Anderson and Moore 1979, sec. 6.4): when j's reading arrives at k and the readings
E of the same instant arrived before k, the filter fuses

    z_j|E = z_j - A z_E = (H_j - A H_E) x_t + (v_j - A v_E),    A = R_jE R_EE^-1,

whose noise has covariance R_jj - A R_Ej (the Schur complement) and is uncorrelated with v_E
and with every other noise; readings of t arriving together at k are correlated with each
other by R_jj' - R_jE R_EE^-1 R_Ej'. The decorrelated readings span what the raw readings
span, so the stacked filter on them is the batch-optimal estimate, with fixed or random
delays and with neglect (E: the readings of t taken before k).

On the stacked model (`latency_stacked.stacked_system`), sensor j gets one extra block of
rows per set E (its *condition*, a subset of the earlier-arriving sensors it is correlated
with, coded by bits: code 0 is the plain reading): H_j - A H_E on the block of its lag.
`coefficients` gives each slot's reading as a combination of the readings of its instant,
which `latency_stacked.wrap` takes from the kept readings.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import NumericalError
from .model import System
from .models import LinearSensor

__all__ = [
    "Conditions",
    "apart_pairs",
    "conditions_of",
    "correlated_refusal",
    "with_conditions",
]


@dataclasses.dataclass(frozen=True)
class Conditions:
    """For each sensor j, `before[j]`: the sensors correlated with j (through the joint R of
    one instant) whose reading of an instant may arrive strictly before j's; a condition of j
    is a subset of them, coded by bits over `before[j]` (bit q: before[j][q])."""

    system: System
    before: tuple[tuple[int, ...], ...]

    def sets(self, j: int) -> list[tuple[int, ...]]:
        """Sensor j's conditions, indexed by code (0: none)."""
        b = self.before[j]
        return [tuple(b[q] for q in range(len(b)) if code >> q & 1) for code in range(1 << len(b))]

    def codes(self, used: np.ndarray, arrive: np.ndarray) -> np.ndarray:
        """Each reading's condition, batch + (K+1, S): the code of the set of readings of its
        instant that were taken (`used`, batch + (K+1, S)) and arrived strictly before it
        (`arrive`, the arrival instants)."""
        out = np.zeros(np.broadcast_shapes(used.shape, arrive.shape), dtype=np.intp)
        for j, b in enumerate(self.before):
            for q, i in enumerate(b):
                out[..., j] |= (used[..., i] & (arrive[..., i] < arrive[..., j])).astype(
                    np.intp
                ) << q
        return out

    def check_whole(self, present: np.ndarray) -> None:
        """Decorrelation conditions on whole readings: a correlated late sensor must have all
        of its components or none at an instant."""
        sl = self.system.sensor_slices
        for i in {i for b in self.before for i in b}:
            p = present[..., sl[i]]
            if (p.any(-1) != p.all(-1)).any():
                # the data, not the definition: the stage names the file (exit 2, one line)
                raise NumericalError(
                    f"sensor {self.system.sensors[i].name!r} is correlated with a sensor "
                    "arriving at another instant and has part of a reading missing: "
                    "decorrelating its readings needs the whole reading"
                )


def conditions_of(
    system: System, arrive: np.ndarray, last: np.ndarray, filters: list[int]
) -> Conditions | None:
    """The conditions of the sensors `filters` (fused by one filter) given their earliest
    and latest arrival instants (K+1, S) per reading; None when no two correlated readings of
    one instant can arrive at different instants (the plain stacked model is then exact)."""
    S = len(system.sensors)
    R, sl = system.R, system.sensor_slices
    linked = np.array([[np.any(R[sl[i], sl[j]]) for j in range(S)] for i in range(S)])
    # v_j - A v_E must be uncorrelated with every reading of its instant fused before, also
    # those correlated with j only through a chain (i ~ l ~ j): E spans j's whole component
    reach = linked.copy()
    for _ in range(S):
        reach = reach | (reach.astype(int) @ reach.astype(int) > 0)
    before: list[tuple[int, ...]] = []
    for j in range(S):
        b = []
        for i in filters:
            if i == j or j not in filters or not reach[i, j]:
                continue
            if np.any(arrive[:, i] < last[:, j]):  # i's reading may come strictly first
                b.append(i)
        before.append(tuple(b))
    if not any(before):
        return None
    return Conditions(system, tuple(before))


def conditioned_sensors(
    cond: Conditions, lags: list[np.ndarray]
) -> tuple[list[LinearSensor], list[tuple[int, int, np.ndarray, np.ndarray]]]:
    """The extra sensors of the stacked model (eq. above), N = (W+1) n, and for each its (j,
    code, lags, coefficients A (dim_j, m) of the readings of its instant: e_j - A_E)."""
    system = cond.system
    n = system.n
    N = (max(int(lj.max()) for lj in lags) + 1) * n
    R, H, sl = system.R, system.H, system.sensor_slices
    out, info = [], []
    names = [s.name for s in system.sensors]
    for j, sen in enumerate(system.sensors):
        lj = lags[j][lags[j] > 0]  # a reading arriving after another left its instant
        for code, E in enumerate(cond.sets(j)):
            if not E or not len(lj):
                continue
            e = np.concatenate([np.arange(system.m)[sl[i]] for i in E])
            Jr = np.arange(system.m)[sl[j]]
            A = np.linalg.solve(R[np.ix_(e, e)], R[np.ix_(e, Jr)]).T  # R_jE R_EE^-1
            coef = np.zeros((sen.dim, system.m))
            coef[:, Jr] = np.eye(sen.dim)
            coef[:, e] -= A
            Hc = coef @ H  # H_j - A H_E
            Rc = R[np.ix_(Jr, Jr)] - A @ R[np.ix_(e, Jr)]
            Rc = (Rc + Rc.T) / 2
            Hs = np.zeros((len(lj) * sen.dim, N))
            for q, lag in enumerate(lj):
                Hs[q * sen.dim : (q + 1) * sen.dim, lag * n : (lag + 1) * n] = Hc
            name = f"{sen.name}|{'+'.join(names[i] for i in E)}"
            out.append(LinearSensor(name, Hs, np.kron(np.eye(len(lj)), Rc)))
            info.append((j, code, lj, coef))
    return out, info


def conditional_cross(
    system: System, j: int, E: tuple[int, ...], jj: int, EE: tuple[int, ...]
) -> np.ndarray | None:
    """Cov(v_j|E, v_jj|EE) of two readings of one instant arriving together (so E = EE):
    R_j,jj - R_jE R_EE^-1 R_E,jj; None when they never arrive together (E != EE, or one
    is in the other's set)."""
    if set(E) != set(EE) or j in EE or jj in E:
        return None
    R, sl = system.R, system.sensor_slices
    a, b = np.arange(system.m)[sl[j]], np.arange(system.m)[sl[jj]]
    C = R[np.ix_(a, b)]
    if E:
        e = np.concatenate([np.arange(system.m)[sl[i]] for i in E])
        C = C - R[np.ix_(a, e)] @ np.linalg.solve(R[np.ix_(e, e)], R[np.ix_(e, b)])
    return C


def with_conditions(
    stacked: System, cond: Conditions, lags: list[np.ndarray], slots: np.ndarray
) -> tuple[System, np.ndarray, np.ndarray]:
    """The stacked model `stacked` (of `cond.system` with sensor lags `lags`, measurement
    slots `slots` (m~, 3): sensor, lag, component) with the conditioned sensors appended:
    (system, slots (m~', 4): sensor, lag, component, condition code, coefficients (m~', m):
    each slot's reading as a combination of the readings of its instant)."""
    system = cond.system
    extra, info = conditioned_sensors(cond, lags)
    m = system.m
    rows = [np.column_stack([slots, np.zeros(len(slots), np.intp)])]
    coefs = [np.eye(m)[slots[:, 2]]]
    for j, code, lj, coef in info:
        d = coef.shape[0]
        start = system.sensor_slices[j].start
        rows += [np.array([(j, int(lag), start + o, code) for lag in lj for o in range(d)])]
        coefs += [np.tile(coef, (len(lj), 1))]
    S0 = len(stacked.sensors)
    cross = dict(stacked.cross_R)
    for a in range(len(info)):
        for b in range(a + 1, len(info)):
            (ja, ca, la, _), (jb, cb, lb, _) = info[a], info[b]
            C = conditional_cross(system, ja, cond.sets(ja)[ca], jb, cond.sets(jb)[cb])
            if C is None or not np.any(C):
                continue
            da, db = C.shape
            out = np.zeros((len(la) * da, len(lb) * db))
            for qa, x in enumerate(la):
                for qb, y in enumerate(lb):
                    if x == y:  # readings of one instant, arriving together
                        out[qa * da : (qa + 1) * da, qb * db : (qb + 1) * db] = C
            if np.any(out):
                cross[(S0 + a, S0 + b)] = out
    out_system = dataclasses.replace(
        stacked, sensors=tuple(stacked.sensors) + tuple(extra), cross_R=cross
    )
    return out_system, np.concatenate(rows).astype(np.intp), np.concatenate(coefs)


def correlated_refusal(system: System, locals_kind: str, arch: str) -> str | None:
    """Why `arch` has no plan with correlated sensors whose readings of one instant may
    arrive at different instants, or None. The centre (CKF) fuses the decorrelated readings
    (module docstring); HKF believes the sensors independent on time as late; a single
    sensor's filter and the locals of a rule that does not read their joint error covariance
    fuse one sensor each, so nothing correlated meets in a filter; the rules that read the
    locals' joint error covariance get it from the affine maps (`core.latency_joint`)."""
    if not system.linear:  # the EKF/UKF lanes rerun an instant with all its arrived readings
        return None  # (`core.nonlinear.late`): no stacked model, their own refusals
    apart = apart_pairs(system)
    if not apart:
        return None
    i, j = (system.sensors[q].name for q in apart[0])
    if system.late == "retrodict" and locals_kind == "centralised":
        return (
            f"architecture {arch}: sensors {i!r} and {j!r} are correlated and arrive apart; "
            "retrodiction (Al1) updates with a late reading as if independent of what the "
            "filter fused: use reprocess or neglect, which fuse the decorrelated reading"
        )
    return None


def apart_pairs(system: System, cross_R: dict | None = None) -> list[tuple[int, int]]:
    """The pairs of correlated sensors whose readings of one instant may arrive at different
    instants (different latencies, or a latency range); correlated as `cross_R` says where
    given (another model's, a truth's), else as the system's."""
    lat = [s.timing.latency for s in system.sensors]
    return [
        (i, j)
        for (i, j), Rij in (system.cross_R if cross_R is None else cross_R).items()
        if np.any(Rij) and (lat[i] != lat[j] or lat[i][0] != lat[i][1])
    ]
