"""Real timing: when each sensor measures, and the model between irregular instants.

A sensor j measures at offset_j, offset_j + period_j, ... within [0, K dt] and loses each
measurement independently with probability dropout_j (DESIGN.md, "Scenario TOML", Timing).

* When every period and offset is a whole number of dt, the instants stay t_k = k dt and a
  sensor's schedule is every period/dt-th instant from offset/dt on (the shared grid of the
  paper, with some sensors silent at some instants).
* Otherwise the instants are the sorted union of t = 0 and every sensor's sampling times, on
  a grid of whole nanoseconds (the resolution of an MCAP log_time, so that two sensors'
  times that agree in the log are one instant), and the intervals between them are irregular.
  The model is then discretised for each interval: for a continuous-time model
  dx = A x dt + dw, E[dw dw'] = Qc dt,

      F(Δ) = expm(A Δ),   Q(Δ) = ∫_0^Δ expm(A s) Qc expm(A s)' ds,

  computed together by Van Loan's method (C. F. Van Loan, "Computing integrals involving the
  matrix exponential", IEEE TAC 23(3), 1978): expm([[-A, Qc], [0, A']] Δ) = [[., M12], [0, M22]]
  gives F = M22' and Q = F M12.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

__all__ = [
    "TIME_UNITS",
    "SensorTiming",
    "Schedule",
    "constant_velocity_continuous",
    "instant_counts",
    "regular_times",
    "schedule",
    "van_loan",
]

#: Times are whole nanoseconds (an MCAP log_time).
NS = 1_000_000_000
#: Nanoseconds per unit of the time units a recorded log may give (``time_unit``).
TIME_UNITS = {"s": NS, "ms": 1_000_000, "us": 1_000, "ns": 1}
#: A period or offset within this relative distance of a whole number of dt is that number.
GRID_RTOL = 1e-9
#: Periods and offsets (other than offset 0) lie in [MIN_PERIOD_S, MAX_PERIOD_S]: one
#: nanosecond is the resolution of the schedule (an MCAP log_time), and 10^9 s (31.7 years)
#: keeps every sampling time far inside the 64-bit nanosecond clock (2^63 ns = 292 years).
MIN_PERIOD_S = 1e-9
MAX_PERIOD_S = 1e9


@dataclass(frozen=True)
class SensorTiming:
    """When one sensor measures: period and offset in seconds (period None: every instant),
    and the probability that a measurement is lost."""

    period: float | None = None
    offset: float = 0.0
    dropout: float = 0.0
    #: Delay (s) from taking a measurement to its arrival at the filters, (min, max): fixed
    #: when equal, else uniform per measurement in [min, max] (DESIGN.md "Late measurements").
    latency: tuple[float, float] = (0.0, 0.0)

    @property
    def late(self) -> bool:
        """Whether this sensor's measurements may arrive after they are taken."""
        return self.latency[1] > 0.0

    @property
    def default(self) -> bool:
        return self.period is None and self.offset == 0.0 and self.dropout == 0.0


@dataclass(frozen=True)
class Schedule:
    """The instants t_k (K+1,) in seconds, and which sensor measures at which instant
    (K+1, S); `regular`: t_k = k dt exactly. Both read only (on a regular grid the times are
    shared, `regular_times`, and sensors measuring at every instant a broadcast True)."""

    times: np.ndarray
    measures: np.ndarray
    regular: bool

    @property
    def steps(self) -> int:
        """K: instants k = 0..K."""
        return len(self.times) - 1


#: (instants, dt) -> the read-only times k dt, while anything holds them
_REGULAR: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def regular_times(instants: int, dt: float) -> np.ndarray:
    """The times k dt, k = 0..instants-1, read only: one array for everything that holds the
    instants of one log at once (its scenario's schedule, the sensors and estimates files,
    the evaluation's systems) instead of one each (8 bytes per instant each: a 4*10^6-instant
    log's memory grew by 32 MB per copy, issue 34)."""
    key = (instants, dt)
    t = _REGULAR.get(key)
    if t is None:
        t = np.arange(instants) * dt
        t.flags.writeable = False
        _REGULAR[key] = t
    return t


def _whole(x: float, dt: float, *, zero: bool) -> int | None:
    """x / dt when it is a whole number (to GRID_RTOL), else None; 0 only when `zero` (an
    offset: a period of a tiny fraction of dt is not "every instant")."""
    q = x / dt
    r = round(q)
    if r == 0 and not (zero and x == 0):
        return None
    return int(r) if abs(q - r) <= GRID_RTOL * max(1.0, abs(q)) else None


def _grid(dt: float, timings: tuple[SensorTiming, ...]) -> list[tuple[int, int]] | None:
    """Each sensor's (period, offset) in whole dt, or None when the instants are irregular."""
    grid = []
    for t in timings:
        p = 1 if t.period is None else _whole(t.period, dt, zero=False)
        o = _whole(t.offset, dt, zero=True)
        if p is None or o is None:
            return None
        grid.append((p, o))
    return grid


def instant_counts(dt: float, steps: int, timings: tuple[SensorTiming, ...]) -> list[int] | None:
    """How many sampling times each sensor has on a horizon of `steps` dt, computed without
    allocating anything (so that a scenario can be refused before its schedule is built);
    None when the instants stay k dt (steps + 1 of them). On irregular instants the schedule
    holds at most 1 + their sum instants (fewer where sensors' times coincide)."""
    if _grid(dt, timings) is not None:
        return None
    counts = []
    for t in timings:
        p = dt if t.period is None else t.period
        counts.append(max(0, math.floor((steps * dt - t.offset) / p * (1 + GRID_RTOL)) + 1))
    return counts


def schedule(dt: float, steps: int, timings: tuple[SensorTiming, ...]) -> Schedule:
    """The instants of a horizon of `steps` dt and each sensor's measuring instants."""
    S = len(timings)
    periods = [dt if t.period is None else t.period for t in timings]
    grid = _grid(dt, timings)
    if grid is not None:
        if all(g == (1, 0) for g in grid):  # every sensor at every instant: no array of it
            measures = np.broadcast_to(np.True_, (steps + 1, S))
        else:
            k = np.arange(steps + 1)
            measures = np.zeros((steps + 1, S), dtype=bool)
            for j, (p, o) in enumerate(grid):
                measures[:, j] = (k >= o) & ((k - o) % p == 0)
        return Schedule(regular_times(steps + 1, dt), measures, True)
    # Irregular: sampling times in whole nanoseconds, their union with t = 0.
    end = round(steps * dt * NS)
    per_sensor = []
    counts = instant_counts(dt, steps, timings) or []
    for p, t, count in zip(periods, timings, counts, strict=True):
        ns = np.rint((t.offset + np.arange(count) * p) * NS).astype(np.int64)
        per_sensor.append(ns[ns <= end])
    all_ns = np.unique(np.concatenate([np.zeros(1, np.int64), *per_sensor]))
    measures = np.zeros((len(all_ns), S), dtype=bool)
    for j, ns in enumerate(per_sensor):
        measures[np.searchsorted(all_ns, ns), j] = True
    return Schedule(all_ns / NS, measures, False)


def van_loan(A: np.ndarray, Qc: np.ndarray, delta: float | np.ndarray):
    """F = expm(A Δ) and Q = ∫_0^Δ expm(A s) Qc expm(A s)' ds by Van Loan's method, for one
    interval Δ or for an array of them at once (F and Q then carry its shape in front)."""
    n = A.shape[0]
    C = np.zeros((2 * n, 2 * n))
    C[:n, :n], C[:n, n:], C[n:, n:] = -A, Qc, A.T
    d = np.asarray(delta, dtype=float)
    powers = _nilpotent_powers(C)
    if powers is not None:
        # expm(C d) = sum_k C^k d^k / k!, a finite sum for a nilpotent C (the kinematic
        # models: constant velocity and its kin): a recorded log's 10^5 distinct intervals
        # cost one product, not 10^5 Pade approximations
        coef = d[..., None] ** np.arange(len(powers)) / np.cumprod([1.0, *range(1, len(powers))])
        E = np.tensordot(coef, powers, axes=1)
    else:
        from scipy.linalg import expm  # here: only irregular instants need it

        E = expm(C * d[..., None, None])  # one batched call for every interval
    F = np.swapaxes(E[..., n:, n:], -1, -2)
    Q = F @ E[..., :n, n:]
    return F, 0.5 * (Q + np.swapaxes(Q, -1, -2))


def _nilpotent_powers(C: np.ndarray) -> np.ndarray | None:
    """[I, C, C^2, ..., C^(N-1)] when C^N is exactly zero for some N <= its size, else None."""
    powers = [np.eye(len(C))]
    for _ in range(len(C)):
        nxt = powers[-1] @ C
        if not nxt.any():
            return np.array(powers)
        powers.append(nxt)
    return None


def constant_velocity_continuous(axes: int, q: float) -> tuple[np.ndarray, np.ndarray]:
    """A and Qc of the constant-velocity model (eqs. 41-42 in continuous time) on `axes`
    independent axes, state per axis [p, v], white acceleration of spectral density q."""
    A = np.kron(np.eye(axes), np.array([[0.0, 1.0], [0.0, 0.0]]))
    Qc = np.kron(np.eye(axes), np.array([[0.0, 0.0], [0.0, q]]))
    return A, Qc
