"""Late measurements: each policy as an ordinary plan on the measurements as they were taken.

A measurement of sensor j taken at instant i arrives at t_i + latency_j; the estimate at the
output instant t_k may use only what has arrived by then (DESIGN.md "Late measurements"). Let
a(j, i) be the first instant k with t_k >= t_i + latency_j and l = a - i its lag (in instants).

*Reprocess* (the filter rewinds to a late measurement's time and refilters everything that
has arrived, in measurement-time order) gives at k the Kalman estimate of x_k from exactly the
arrived set {(j, i): a(j, i) <= k}. That estimate is a Kalman filter on the *stacked state*
X_k = [x_k; x_{k-1}; ...; x_{k-W}] (W the largest lag; X_k = F~ X_{k-1} + [w; 0; ...]) whose
measurement at k is what arrives at k: the reading of sensor j taken l instants ago is
H_j x_{k-l} + v, a row of H~ on the l-th block of X_k (the fixed-lag augmentation of
Anderson and Moore, "Optimal Filtering", 1979, ch. 7; Bar-Shalom, Chen, Mallick 2004, sec. 2,
note that reprocessing is optimal). Each reading arrives once, so the stacked model's noise is
white, and its filter is exactly the rewind-and-refilter estimate, with a bounded history: W
instants of state.

*Neglect* drops a measurement older than the filter's last update (the newest measurement
time processed): processing the rest in arrival order is processing them in time order, so
neglect is reprocessing of the accepted measurements.

Both are filters on the stacked model fed with the readings as they arrive, i.e. linear maps
of the measurements as taken once the plan keeps the W last readings in its internal state:

    s_k = [s~_k; z_k; z_{k-1}; ...; z_{k-W+1}],    s~_k = T~ s~_{k-1} + U~ z~_k,

z~_k (what arrives at k) being a selection of z_k and the kept readings. So the executor, the
per-run and history-node paths and the exact analysis (`core.exact`: the joint moments of the
true state and s_k) take it as any other plan, the truth being the scenario's own model.

Where each message carries its own R (`System.Rs`, eq. 31 per instant), the stacked model's
noise at k is that of the readings arriving then: a slot of lag l has the R of instant k - l,
the instant it was taken (`latency_stacked.stacked_noise`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .architectures import Plan, definition, parse_arch
from .architectures.filters import constant_tail
from .late_policy import accepted, arrival_steps, is_late, random_delays
from .latency_corr import Conditions, apart_pairs, conditions_of, with_conditions
from .latency_joint import joint_fused_plan
from .latency_stacked import fused_plan, stacked_noise, stacked_system, wrap
from .model import System

__all__ = ["LateModel", "lag_pairs", "lags_of", "stacked_system"]


@dataclass
class LateModel:
    """The late sensors of one model on one horizon: when each measurement arrives, and the
    plans of the stacked model wrapped as plans on the measurements as taken.

    `arrive` (K+1, S): the instant index at which the measurement sensor j takes at instant
    i arrives (K+1: never, within the horizon) with fixed latencies; `lags[j]`: the lags its
    readings may arrive with; `times` the instants (s); `per_run`: the delays differ from run
    to run (a latency range), so the arrivals come with each block's data (`build`).
    """

    system: System
    steps: int
    arrive: np.ndarray
    lags: list[np.ndarray]
    times: np.ndarray
    per_run: bool = False
    #: (K+1, S): the latest instant each reading may arrive at (None: `arrive`)
    last: np.ndarray | None = field(default=None, repr=False)
    stacked: System = field(init=False, repr=False)
    #: (m~, 3): for each component of the stacked measurement, its sensor, lag and component
    #: of z (eq. 30)
    slots: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.stacked = stacked_system(self.system, self.lags)
        rows = []
        for j, (sl, lj) in enumerate(zip(self.system.sensor_slices, self.lags, strict=True)):
            for lag in lj:
                rows += [(j, int(lag), o) for o in range(sl.start, sl.stop)]
        self.slots = np.array(rows, dtype=np.intp).reshape(-1, 3)
        if self.system.Rs is not None:  # each reading's own R, on the stacked slots
            self.stacked = self.with_noise(self.stacked, self.slots, None)

    def with_noise(self, stacked: System, slots: np.ndarray, coef: np.ndarray | None) -> System:
        """`stacked` (slots (m~, 3+), `coef`) with the per-instant R of the whole run's
        readings (`latency_stacked.stacked_noise`; a long log's blocks form theirs per block,
        `core.latency_blocks`)."""
        Rs = np.asarray(self.system.Rs)
        return dataclasses.replace(stacked, Rs=stacked_noise(Rs, self.system.R, slots, coef, 0))

    @classmethod
    def of(cls, system: System, steps: int, times: np.ndarray | None) -> LateModel | None:
        """The late model of `system` on the instants `times` (default k dt), or None when no
        sensor is late (the plans are then the plain ones, bit for bit)."""
        if not is_late(system):
            return None
        times = np.arange(steps + 1) * system.dt if times is None else np.asarray(times, float)
        lat = np.array([s.timing.latency for s in system.sensors])  # (S, 2)
        arrive = arrival_steps(times, times[:, None] + lat[None, :, 0])
        last = arrival_steps(times, times[:, None] + lat[None, :, 1])  # the latest arrival
        K1 = steps + 1
        pairs = lag_pairs(arrive, last, 0, K1)
        lags = [lags_of(p, K1) for p in pairs]
        return cls(system, steps, arrive, lags, times, random_delays(system), last)

    @classmethod
    def of_lags(
        cls,
        system: System,
        steps: int,
        lags: list[np.ndarray],
        times: np.ndarray,
        conditions: Conditions | None,
    ) -> LateModel:
        """The late model of `system` whose sensors' lags and decorrelation conditions were
        found elsewhere (over a long log block by block, `core.latency_blocks`): it has no
        arrival instants of its own (`arrive` empty), so `stacked_mask` takes them given."""
        arrive = np.zeros((0, len(system.sensors)), dtype=np.intp)
        model = cls(system, steps, arrive, lags, times, random_delays(system), None)
        centre = None
        if conditions is not None:
            got = with_conditions(model.stacked, conditions, lags, model.slots)
            centre = (*got, conditions)
        model._centre = centre
        return model

    def centre_model(self) -> tuple | None:
        """The decorrelated stacked model of the centre (`_centre_model`), made once."""
        if not hasattr(self, "_centre"):
            self._centre = _centre_model(self)
        return self._centre

    @property
    def window(self) -> int:
        """W: the instants of state the filter keeps beside the current one (its history)."""
        return max(int(lj.max()) for lj in self.lags)

    def stacked_mask(
        self,
        present: np.ndarray,
        filters: list[list[int]],
        arrive: np.ndarray | None = None,
        centre: tuple | None = None,
    ) -> np.ndarray:
        """The presence mask of the stacked measurement, batch + (K+1, m~): the reading of
        slot (j, l) is there at k when sensor j measured that component at k - l, it arrives
        at k (`arrive`, batch + (K+1, S), default the fixed latencies') and (neglect) it is not
        older than the last update of the filter that fuses it (`filters`: the sensors each
        filter fuses). `centre` (`centre_model`): the slots of the model with decorrelated
        readings, each there when its condition is the set of its instant's readings taken
        before it."""
        K1 = present.shape[-2]
        arrive = self.arrive if arrive is None else arrive
        batch = np.broadcast_shapes(present.shape[:-2], arrive.shape[:-2])
        present = np.broadcast_to(present, batch + present.shape[-2:])
        took = np.stack(
            [present[..., sl].any(-1) for sl in self.system.sensor_slices], axis=-1
        )  # batch + (K+1, S): the sensor measured at i
        arrive = np.broadcast_to(arrive, took.shape)
        if self.system.late == "neglect":
            ok = np.zeros_like(took)
            for g in filters:
                ok[..., g] = accepted(took[..., g], arrive[..., g], self.window)
            took = took & ok
        slots = self.slots if centre is None else centre[1]
        j, lag, o = slots[:, :3].T
        if centre is not None:
            cond = centre[3]
            cond.check_whole(present)
            code = cond.codes(took, arrive)
        out = np.zeros(present.shape[:-2] + (K1, len(slots)), dtype=bool)
        for c, (jc, lc, oc) in enumerate(zip(j, lag, o, strict=True)):  # slot c, over every k
            i = slice(0, max(K1 - lc, 0))  # the readings taken at i = k - lag, k >= lag
            here = present[..., i, oc] & took[..., i, jc]
            here &= arrive[..., i, jc] == np.arange(lc, K1)
            if centre is not None:
                here &= code[..., i, jc] == slots[c, 3]
            out[..., lc:, c] = here
        return out

    def filters_of(self, arch: str) -> tuple[str, str, list[list[int]]]:
        """`arch`'s base name, kind of locals and the sensors each of its filters fuses."""
        names = [s.name for s in self.system.sensors]
        base, sensor = parse_arch(arch, names)
        locals_kind = definition(base).locals
        if sensor is not None:  # one filter on one sensor
            return base, locals_kind, [[names.index(sensor)]]
        if locals_kind == "per-sensor":  # a local filter per sensor
            return base, locals_kind, [[j] for j in range(len(names))]
        return base, locals_kind, [list(range(len(names)))]  # one filter (or a centre)

    def arrivals_of(self, arrival: np.ndarray | None) -> np.ndarray | None:
        """The arrival instants of readings that arrived at `arrival` (runs, K+1, S) s (None:
        the fixed latencies'), checked against the model's lags."""
        if arrival is None:
            return None
        K1 = self.steps + 1
        arrive = arrival_steps(self.times, arrival)
        for j, lj in enumerate(self.lags):  # the readings' own lags must be among the model's
            a = arrive[..., j]
            lag = (a - np.arange(K1))[a < K1]
            if not np.isin(lag, lj).all():
                name = self.system.sensors[j].name
                raise ValueError(f"sensor {name}: a reading arrives outside its latency range")
        return arrive

    def build(
        self, build, arch: str, present: np.ndarray | None, arrival: np.ndarray | None = None, **kw
    ) -> Plan:
        """`arch`'s plan on the measurements as taken: `build(system, arch, steps, mask,
        **kw)` (`architectures.build_plan`) compiles it on the stacked model, then its maps
        are wrapped to keep the last W readings (`wrap`). `arrival` (runs, K+1, S): when each
        reading of the block's runs arrived (s), for delays that differ per run: the plan
        is then per run."""
        if self.per_run and arrival is None:
            raise ValueError("random delays: give the arrival times of the block's readings")
        K1 = self.steps + 1
        if present is None:
            present = np.ones((K1, self.system.m), dtype=bool)
        kw.pop("groups", None)  # the stacked mask groups the runs by its own histories
        base, locals_kind, filters = self.filters_of(arch)
        arrive = self.arrivals_of(arrival)
        if self.system.late == "retrodict":
            from .retrodict_fused import late_retrodict_plan

            arr = self.arrive if arrive is None else arrive
            criterion = kw.get("criterion", "trace")
            return late_retrodict_plan(
                self.system, arch, base, present, arr, filters, self.lags, criterion
            )
        centre = self.centre_model() if locals_kind == "centralised" else None
        mask = self.stacked_mask(present, filters, arrive, centre)
        with constant_tail():  # past the window the mask repeats: the steady shortcut applies
            if centre is not None:  # correlated readings of one instant arriving apart
                inner = build(centre[0], arch, self.steps, mask, **kw)
                m, W, n = self.system.m, self.window, self.system.n
                return wrap(inner, centre[1], m, W, n, centre[2], self.system)
            if locals_kind == "per-sensor" and definition(base).joint and apart_pairs(self.system):
                # correlated readings enter two locals at two instants: J from the maps
                criterion = kw.get("criterion", "trace")
                args = (self.system, self.stacked, base, mask, self.slots, self.window)
                return joint_fused_plan(*args, criterion)
            if locals_kind == "per-sensor":  # the rule on the locals' current blocks
                criterion = kw.get("criterion", "trace")
                nodes = kw.get("history_nodes", False)
                n = self.system.n
                inner = fused_plan(self.stacked, base, mask, criterion, n, nodes)
            else:
                inner = build(self.stacked, arch, self.steps, mask, **kw)
        m, W, n = self.system.m, self.window, self.system.n
        return wrap(inner, self.slots, m, W, n, system=self.system)


def lag_pairs(arrive: np.ndarray, last: np.ndarray, first: int, K1: int) -> list[np.ndarray]:
    """Per sensor, the distinct spans (earliest lag, latest lag), coded lo (K1+1) + hi, of the
    readings taken at instants first, first+1, ... that arrive at `arrive` (rows, S) at the
    earliest and `last` at the latest (instant indices; K1: never, within the horizon)."""
    out = []
    i = np.arange(first, first + len(arrive))
    for j in range(arrive.shape[1]):
        got = arrive[:, j] < K1
        # every lag between the earliest and the latest arrival (within the horizon)
        lo, hi = arrive[got, j] - i[got], np.minimum(last[got, j], K1 - 1) - i[got]
        out.append(np.unique(lo.astype(np.int64) * (K1 + 1) + hi))  # few distinct spans
    return out


def lags_of(pairs: np.ndarray, K1: int) -> np.ndarray:
    """A sensor's lags: every lag of its spans (`lag_pairs`), 0 where it has none."""
    spans = [np.arange(p // (K1 + 1), p % (K1 + 1) + 1) for p in pairs.tolist()]
    return np.unique(np.concatenate(spans or [np.zeros(1, np.intp)])).astype(np.intp)


def _centre_model(model: LateModel) -> tuple | None:
    """(stacked system, slots, coefficients, conditions) of the one filter fusing every
    sensor where correlated readings of one instant may arrive apart (`core.latency_corr`),
    else None (the plain stacked model is exact)."""
    last = model.arrive if model.last is None else model.last
    S = len(model.system.sensors)
    cond = conditions_of(model.system, model.arrive, last, list(range(S)))
    if cond is None:
        return None
    stacked, slots, coef = with_conditions(model.stacked, cond, model.lags, model.slots)
    if model.system.Rs is not None:
        # the decorrelating A = R_jE R_EE^-1 are the nominal R's: with each message's own R
        # the decorrelated readings are not white across instants, so this filter is not the
        # batch-optimal one (its P is not its error covariance); it stays an affine map of
        # the readings, which the plans' exact analysis takes as any other
        stacked = model.with_noise(stacked, slots, coef)
    return stacked, slots, coef, cond
