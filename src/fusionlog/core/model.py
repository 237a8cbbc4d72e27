"""The linear Gaussian system of eqs. (12)-(13) and its sensors, as plain immutable data.

x_{k+1} = F x_k + G w_k,   w_k ~ N(0, Q)
z_k^(j) = H^(j) x_k + v_k^(j),   v_k ~ N(0, R) with R the block matrix of eq. (31), whose
off-diagonal blocks hold the cross-covariances between sensors (the paper allows dependent v^(j)).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from .intervals import MotionNoise, PerInstant, PerInterval, Transitions, VanLoan
from .models import LinearMotion, LinearSensor, MotionModel, NotLinear, SensorModel
from .timing import Schedule, schedule

#: The linear sensor of eq. (13) (`core.models.LinearSensor`), by its historical name.
Sensor = LinearSensor


@dataclass(frozen=True)
class Prior:
    """Gaussian p(x_0 | z_{-1}) = N(mean, cov)."""

    mean: np.ndarray  # (n,)
    cov: np.ndarray  # (n, n)


@dataclass(frozen=True)
class System:
    """Model and sensors shared by the simulator (truth) and the estimators (filter model).

    `prior` is what the filters start from; None means "no prior information" and the filters
    start exactly in information form with zero information. `initial` is the distribution the
    truth x_0 is drawn from; it defaults to the prior (the paper uses one for both).
    `cross_R[(i, j)]` (i < j) is E[v^(i) v^(j)^T].

    `continuous` is the model in continuous time, (A, Qc), when it has one (the
    constant-velocity and continuous kinds); F and Q are then its discretisation over dt.
    On irregular instants (`on_times`) the transition from instant k-1 to k is `Fs[k-1]`, its
    process noise (in state space, G Q G^T) `Qs[k-1]`; None: the same F, G Q G^T every step.
    `on_times` gives them as `core.intervals.PerInterval`s, formed for the intervals asked for
    (a block of time), not held for the whole log; arrays are taken too.
    """

    F: np.ndarray
    Q: np.ndarray
    sensors: tuple[SensorModel, ...]
    prior: Prior | None = None
    G: np.ndarray | None = None
    cross_R: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    initial: Prior | None = None
    dt: float = 1.0
    state_names: tuple[str, ...] = ()
    continuous: tuple[np.ndarray, np.ndarray] | None = None
    Fs: np.ndarray | PerInterval | None = None  # (K, n, n)
    Qs: np.ndarray | PerInterval | None = None  # (K, n, n)
    #: The stacked measurement noise covariance of eq. (31) at each instant (K+1, m, m), where
    #: it varies (a recorded log whose messages carry their own covariance); None: R always.
    #: A long log's is a `core.intervals.PerInstant`, formed for the instants asked for.
    Rs: np.ndarray | PerInstant | None = None
    #: A nonlinear motion model (`core.models`, e.g. the coordinated turn), which then replaces
    #: F, Q (kept as its linearisation at the zero state over dt and its Q(dt)); None: F, Q.
    motion_model: MotionModel | None = None
    #: The local filter of every architecture when a model is nonlinear: "EKF" | "UKF" (None:
    #: the KF), and the UKF's (alpha, beta, kappa) (DESIGN.md, "Nonlinear sensors and motion").
    filter: str | None = None
    ukf: tuple[float, float, float] = (1.0, 2.0, 0.0)
    #: The cost covariance intersection minimises, "trace" | "det" ([estimate] ci_criterion).
    ci_criterion: str = "trace"
    #: With a nonlinear motion on irregular instants (`on_times`), the interval before each
    #: instant k >= 1 (K,); None: dt.
    intervals: np.ndarray | None = None
    #: What the filters do with late measurements (`[[sensors]] latency`): "reprocess" |
    #: "retrodict" | "neglect" (DESIGN.md "Late measurements", `core.latency`).
    late: str = "reprocess"

    def __post_init__(self) -> None:
        if not self.state_names:
            object.__setattr__(self, "state_names", tuple(f"x{i + 1}" for i in range(self.n)))

    @property
    def n(self) -> int:
        return self.F.shape[0]

    @property
    def GQG(self) -> np.ndarray:
        """Process noise covariance in state space, G Q G^T."""
        if self.G is None:
            return self.Q
        return self.G @ self.Q @ self.G.T

    @property
    def motion(self) -> MotionModel:
        """The motion model (`core.models`): `motion_model`, or the linear one of F, G Q G^T over
        dt (and the continuous model, for other intervals)."""
        if self.motion_model is not None:
            return self.motion_model
        return LinearMotion(self.F, self.GQG, self.dt, self.continuous)

    @property
    def linear(self) -> bool:
        """Whether every sensor (and the motion) is linear: what compiled plans and the exact
        analysis need."""
        return self.motion.linear and all(s.linear for s in self.sensors)

    def linear_measurement(self) -> np.ndarray:
        """The stacked measurement matrix of eq. (30), (m, n), asked of the sensor models; the
        one place that refuses a nonlinear sensor (`NotLinear`) where a matrix is needed."""
        for s in self.sensors:
            if not s.linear:
                raise NotLinear(
                    f"sensor {s.name} ({s.kind}) is nonlinear: it has no measurement matrix "
                    "(the compiled plans and the exact analysis need linear sensors)"
                )
        return np.vstack([s.H for s in self.sensors])

    def h(self, x: np.ndarray) -> np.ndarray:
        """The stacked noise-free measurement (eq. 30) of states x (..., n): (..., m)."""
        if self.linear:  # one product: what the simulation always computed
            return x @ self.H.T
        return np.concatenate([s.h(x) for s in self.sensors], axis=-1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """The stacked measurement Jacobian at states x (..., n): (..., m, n)."""
        return np.concatenate([s.jacobian(x) for s in self.sensors], axis=-2)

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """The stacked innovation z - z_hat (..., m), each sensor's asked of its model (angles
        wrapped)."""
        if self.linear:
            return z - z_hat
        parts = [
            s.residual(z[..., sl], z_hat[..., sl])
            for s, sl in zip(self.sensors, self.sensor_slices, strict=True)
        ]
        return np.concatenate(parts, axis=-1)

    @property
    def time_invariant(self) -> bool:
        """The same F and G Q G^T between every two instants, and the same R at every one."""
        return self.Fs is None and self.Rs is None

    def F_at(self, k: int) -> np.ndarray:
        """Transition from instant k-1 to instant k (k >= 1)."""
        return self.F if self.Fs is None else self.Fs[k - 1]

    def dt_at(self, k: int) -> float:
        """The interval from instant k-1 to instant k (k >= 1) of a nonlinear motion."""
        return self.dt if self.intervals is None else float(self.intervals[k - 1])

    def propagate(self, x: np.ndarray, k: int) -> np.ndarray:
        """The noise-free transition of states x (..., n) from instant k-1 to k: F x, or f(x)."""
        if self.motion_model is None:
            return x @ self.F_at(k).T
        return self.motion_model.f(x, self.dt_at(k))

    def GQG_at(self, k: int) -> np.ndarray:
        """Process noise covariance (state space) from instant k-1 to instant k (k >= 1)."""
        return self.GQG if self.Qs is None else self.Qs[k - 1]

    def transitions(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """`F_at(k)` and `GQG_at(k)` of the instants k = a+1..b at once, (b - a, n, n) each,
        read only (views where the system has one F or G Q G^T; on irregular instants formed
        for these intervals alone, `core.intervals`)."""
        n = self.n
        Fs = self.Fs[a:b] if self.Fs is not None else np.broadcast_to(self.F, (b - a, n, n))
        Qs = self.Qs[a:b] if self.Qs is not None else np.broadcast_to(self.GQG, (b - a, n, n))
        return Fs, Qs

    def schedule(self, steps: int) -> Schedule:
        """The instants of a horizon of `steps` dt and when each sensor measures."""
        return schedule(self.dt, steps, tuple(s.timing for s in self.sensors))

    def R_at(self, k: int) -> np.ndarray:
        """The stacked measurement noise covariance (eq. 31) at instant k."""
        return self.R if self.Rs is None else self.Rs[k]

    def on_times(self, times: np.ndarray) -> System:
        """The system on the instants `times` (K+1,): itself when they are k dt, else with the
        continuous model discretised for every interval (`timing.van_loan`, one matrix
        exponential per distinct interval), formed a stretch of intervals at a time when asked
        for (`core.intervals.PerInterval`: `Fs`, `Qs` hold the times, not K matrices). A model
        given by F and Q alone has no other discretisation: its F and Q apply between every
        two instants, whatever their times (a scenario with irregular instants refuses such a
        model when it is loaded)."""
        times = np.asarray(times, dtype=float)
        if self.motion_model is not None:  # f(x, dt) and Q(dt) take any interval
            if _is_grid(times, self.dt):
                return dataclasses.replace(self, intervals=None, Qs=None)
            source = Transitions(times, MotionNoise(self.motion_model.Q, self.n))
            return dataclasses.replace(self, intervals=np.diff(times), Qs=PerInterval(source, 1))
        if self.continuous is None or _is_grid(times, self.dt):
            return self if self.Fs is None else dataclasses.replace(self, Fs=None, Qs=None)
        from .timing import van_loan

        A, Qc = self.continuous
        lo, hi = _interval_range(times)
        if len(times) > 1 and hi - lo <= 1e-9 * abs(times[1] - times[0]):
            # A regular log (times on a grid to rounding): one interval, so a time-invariant
            # system, whose Riccati recursion reaches the steady state that the plans repeat
            # instead of recomputing 10^6 identical gains.
            dt = float(np.mean(np.diff(times)))
            F1, Q1 = van_loan(A, Qc, dt)
            return dataclasses.replace(self, F=F1, Q=Q1, G=None, dt=dt, Fs=None, Qs=None)
        source = Transitions(times, VanLoan(A, Qc))
        return dataclasses.replace(self, Fs=PerInterval(source, 0), Qs=PerInterval(source, 1))

    @property
    def truth_initial(self) -> Prior:
        init = self.initial if self.initial is not None else self.prior
        if init is None:
            raise ValueError("the truth needs an initial distribution when there is no prior")
        return init

    @property
    def sensor_slices(self) -> tuple[slice, ...]:
        """Rows of each sensor in the stacked measurement vector of eq. (30)."""
        out, start = [], 0
        for s in self.sensors:
            out.append(slice(start, start + s.dim))
            start += s.dim
        return tuple(out)

    @property
    def m(self) -> int:
        """Length of the stacked measurement vector."""
        return sum(s.dim for s in self.sensors)

    @property
    def H(self) -> np.ndarray:
        """Stacked measurement matrix of eq. (30) (`linear_measurement`)."""
        return self.linear_measurement()

    @property
    def R(self) -> np.ndarray:
        """Block measurement noise covariance, eq. (31) with cross-covariance blocks."""
        sl = self.sensor_slices
        R = np.zeros((self.m, self.m))
        for i, s in enumerate(self.sensors):
            R[sl[i], sl[i]] = s.R
        for (i, j), Rij in self.cross_R.items():
            R[sl[i], sl[j]] = Rij
            R[sl[j], sl[i]] = Rij.T
        return R

    def subset(self, indices: list[int]) -> System:
        """The same system seen by a subset of the sensors (e.g. one sensor for SKF)."""
        pos = {j: p for p, j in enumerate(indices)}
        sl = self.sensor_slices
        rows = np.concatenate([np.arange(self.m)[sl[j]] for j in indices]).astype(int)
        cross = {
            (pos[i], pos[j]): Rij for (i, j), Rij in self.cross_R.items() if i in pos and j in pos
        }
        Rs = None if self.Rs is None else self.Rs[:, rows][:, :, rows]
        sensors = tuple(self.sensors[j] for j in indices)
        return dataclasses.replace(self, sensors=sensors, cross_R=cross, Rs=Rs)

    def undetermined_states(self) -> list[int]:
        """The states that the sensors (all of them, every instant) never determine through
        the motion: those with a component in the unobservable subspace of (F, H), the null
        space of O = [H; HF; ...; HF^(n-1)] (Kalman's rank test). Without a prior no filter
        then ever has a covariance. O's columns and rows are scaled to unit size first, so the
        rank does not depend on the states' units. Empty where O is not finite (undecided)."""
        n = self.n
        with np.errstate(over="ignore", invalid="ignore"):
            rows = [self.H]
            for _ in range(n - 1):
                rows.append(rows[-1] @ self.F)
            O = np.vstack(rows)
        if not np.isfinite(O).all():
            return []
        # scaled by the largest magnitudes (a 2-norm could overflow on entries of 1e200)
        keep = np.abs(O).max(axis=0) > 0  # a state no row involves is undetermined
        O = O[:, keep] / np.abs(O[:, keep]).max(axis=0)
        O = O[np.abs(O).max(axis=1) > 0]
        O = O / np.abs(O).max(axis=1)[:, None]
        cols = np.flatnonzero(keep)
        if not len(O):
            return list(range(n))
        _, sv, Vt = np.linalg.svd(O)
        rank = int((sv > max(O.shape) * np.finfo(float).eps * sv[0]).sum())
        weak = (Vt[rank:] ** 2).sum(axis=0) > 1e-12  # a component in the null space
        return sorted([int(i) for i in np.flatnonzero(~keep)] + [int(i) for i in cols[weak]])

    def sensor_index(self, name: str) -> int:
        for j, s in enumerate(self.sensors):
            if s.name == name:
                return j
        raise KeyError(name)


def _is_grid(times: np.ndarray, dt: float, block: int = 1 << 16) -> bool:
    """times_k == k dt for every k, a block of instants at a time (no array of the log's
    length: `np.array_equal(times, np.arange(K + 1) * dt)`)."""
    return all(
        np.array_equal(times[a : a + block], np.arange(a, min(a + block, len(times))) * dt)
        for a in range(0, len(times), block)
    )


def _interval_range(times: np.ndarray, block: int = 1 << 16) -> tuple[float, float]:
    """The smallest and largest interval between consecutive instants (0, 0 for fewer than
    two), a block of instants at a time."""
    lo, hi = np.inf, -np.inf
    for a in range(0, len(times) - 1, block):
        d = np.diff(times[a : a + block + 1])
        lo, hi = min(lo, d.min()), max(hi, d.max())
    return (0.0, 0.0) if lo > hi else (float(lo), float(hi))


def constant_velocity(dt: float, n0: float) -> tuple[np.ndarray, np.ndarray]:
    """F and Q of eqs. (41)-(42): x = [position, velocity], Q = [[dt^3/3, dt^2/2], [dt^2/2, dt]] N0.

    N0 is the noise power spectral density (the paper uses N0 = 0.16 Ts).
    """
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]) * n0
    return F, Q


def nominal_R(covariances: np.ndarray) -> np.ndarray:
    """The nominal R (m, m) of a sensor whose readings carry their own covariance and that has
    no R of its own: the mean of its messages' finite covariances (N, m, m). The one rule
    (the import records it in the resolved scenario; the filters use it wherever a message
    has none)."""
    return nominal_R_of([covariances])


def nominal_R_of(blocks: Iterable[np.ndarray]) -> np.ndarray:
    """`nominal_R` of the messages' covariances given block by block (a long log's import),
    bit for bit: numpy sums along the first axis in order, so the finite ones are summed in
    order across the blocks and divided by their count, as ``mean(axis=0)`` does."""
    acc, count, shape = None, 0, (0, 0)
    for c in blocks:
        shape = c.shape[1:]
        have = c[np.isfinite(c).all(axis=(-2, -1))]
        if len(have):
            acc = np.add.reduce(have if acc is None else np.concatenate((acc[None], have)), axis=0)
            count += len(have)
    return np.full(shape, np.nan) if acc is None else acc / count


__all__ = [
    "NotLinear",
    "Prior",
    "Sensor",
    "System",
    "ajgl2009",
    "constant_velocity",
    "nominal_R",
    "nominal_R_of",
]


def ajgl2009(ts: float = 1.0, n_sensors: int = 3) -> System:
    """The paper's numerical example (Section VI): N0 = 0.16 Ts, R = 1, prior N([100, -1], I)."""
    F, Q = constant_velocity(ts, 0.16 * ts)
    H = np.array([[1.0, 0.0]])
    sensors = tuple(Sensor(f"s{j + 1}", H, np.array([[1.0]])) for j in range(n_sensors))
    return System(
        F=F,
        Q=Q,
        sensors=sensors,
        prior=Prior(np.array([100.0, -1.0]), np.eye(2)),
        dt=ts,
        state_names=("position", "velocity"),
    )
