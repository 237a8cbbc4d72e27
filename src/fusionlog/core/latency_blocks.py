"""A long one-run log with late sensors in blocks of time without plans (issue 34): the
plan-free late path (`latency_replay`: the stacked model of `core.latency`, its readings z~
laid out per instant) carried from block to block, for what the short steady plans of
`latency_long` cannot stand for -- delays drawn per reading or recorded (a replay's
``arrival = "log_time"``), and readings missing (dropouts, own rates, gaps).

The stacked filter X_k = [x_k; ...; x_{k-W}] (Anderson and Moore 1979, ch. 7) is a Kalman
filter like any other, so `architectures.replay_blocks.ReplayBlocks` carries it across a block
edge as it carries an on-time one (its covariance and mean at the block's last instant). What
else crosses the edge is the raw readings: the stacked reading of slot (j, l) at k is the
reading of instant k - l where it arrives at k, so a block [k0, k1) is laid out on the window
[k0 - W, k1) of raw readings and their arrival times, the W rows before k0 kept from the block
before (`_Window`). Neglect's acceptance of a reading depends only on readings of its instant or
later (`late_policy.accepted`), all of them in that window, so the window's mask is the whole
log's. The lags of each sensor and the decorrelation conditions of correlated readings arriving
apart (`latency_corr`) are the whole log's, found block by block before (`LateBlocks.of`).

Estimates: each block's stacked readings through `ReplayBlocks.estimates`; the estimate of x_k
is the stacked one's first block. The exact analysis, where the truth is the filters' model:
the error covariances of the stacked filters under their own model (`ReplayBlocks.
error_covariances`, `exact_replay`), the marginal of x_k -- the analysis conditional on the
drawn or recorded delays, as the plans' of the run's arrival pattern.

Covered, under reprocess and neglect: as `latency_replay` -- CKF (on the decorrelated readings
where correlated ones arrive apart), HKF and SKF -- and the per-sensor rules (MSC, MSC-GMF, CI,
AVG, ICI, EI): one local stacked filter per sensor (neglect's acceptance per local), carried
as `ReplayBlocks` carries the on-time locals with their joint error covariance J of eq. (35),
the rule fusing their current blocks at each instant (`latency_stacked.current_block_rule`,
the plans' `fused_plan` rule; no rule keeps a state of its own: CI's, ICI's and EI's weights
are per instant). Where correlated readings of one instant arrive apart, the stacked noise is
correlated across time: J (MSC-GMF's and AVG's weights, every rule's exact analysis) and HKF's
error covariance then keep the raw noises still to be read (`core.latency_apart`, as the
plans' `latency_joint` maps keep the readings). A log whose messages carry their own R
(`System.Rs`, read per block from its spool): the stacked R of each block from the raw R of
its instants and the W before (`latency_stacked.stacked_noise`: a slot of lag l at k has the
R of instant k - l), the raw noises kept with the R of their instant. Not here (None: the
whole run, the plans): retrodiction, FBS, fixed latencies on a steady model with every
reading present (the steady plans of `latency_long`), and the centre where correlated
readings arrive apart with each message's R (`LateBlocks.of`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .architectures import definition, parse_arch
from .architectures.plan import Estimate
from .architectures.replay import _Replay
from .architectures.replay_blocks import ReplayBlocks, system_window
from .late_policy import arrival_steps, is_late, random_delays
from .latency import LateModel, lag_pairs, lags_of
from .latency_apart import ApartReplay, selection
from .latency_corr import Conditions, apart_pairs, conditions_of, with_conditions
from .latency_replay import stacked_readings
from .latency_stacked import current_block_rule, stacked_noise, stacked_system
from .model import System

__all__ = ["LATE_BLOCK_BYTES", "LateBlocks"]

#: The masked H and R a block of the stacked filters may hold (bytes): a block of time is cut
#: into sub-blocks below it (the stacked model has W + 1 times the states and a row block per
#: lag).
LATE_BLOCK_BYTES = 1 << 25

#: The kinds of architecture (`definition.LOCALS`) the path takes: not the smoother, whose
#: backward pass would run on the stacked model from the log's end.
_KINDS = ("centralised", "hierarchical", "single", "per-sensor")


def _geometry(
    system: System, times: np.ndarray, block: int
) -> tuple[list[np.ndarray], Conditions | None]:
    """Each sensor's lags and the centre's decorrelation conditions over the instants `times`
    (`LateModel.of`'s, found block by block: the arrival instants of one block at a time)."""
    K1, S = len(times), len(system.sensors)
    lat = np.array([s.timing.latency for s in system.sensors])  # (S, 2)
    pairs: list[set[int]] = [set() for _ in range(S)]
    before: list[set[int]] = [set() for _ in range(S)]
    for a in range(0, K1, block):
        t = times[a : a + block, None]
        arrive, last = arrival_steps(times, t + lat[:, 0]), arrival_steps(times, t + lat[:, 1])
        for j, p in enumerate(lag_pairs(arrive, last, a, K1)):
            pairs[j] |= set(p.tolist())
        cond = conditions_of(system, arrive, last, list(range(S)))
        for j, b in enumerate(cond.before if cond is not None else ()):
            before[j] |= set(b)
    lags = [lags_of(np.array(sorted(p), dtype=np.int64), K1) for p in pairs]
    if not any(before):
        return lags, None
    return lags, Conditions(system, tuple(tuple(sorted(b)) for b in before))


def late_model(system: System, steps: int, times: np.ndarray, block: int, conditions: bool):
    """The late model of one run of instants 0..`steps` at `times` (s) for the blocked paths
    (this module's and `retrodict_blocks`'): each sensor's lags found in blocks of `block`
    instants (`_geometry`), with the centre's decorrelation conditions where `conditions`."""
    lags, cond = _geometry(system, times, block)
    shape = dataclasses.replace(system, Fs=None, Qs=None, intervals=None, Rs=None)
    late = LateModel.of_lags(shape, steps, lags, times, cond if conditions else None)
    late.system = system
    return late


def late_kinds(system: System, archs: Sequence[str], retrodict: bool) -> list[str] | None:
    """The kinds of locals of `archs` (`definition.locals`) where a blocked late path may take
    them: late sensors of a linear model with a prior, retrodicted or not (`retrodict`);
    None otherwise (before any reading is seen)."""
    if not is_late(system) or (system.late == "retrodict") != retrodict:
        return None
    if system.prior is None or not system.linear or system.motion_model is not None:
        return None
    names = [s.name for s in system.sensors]
    try:
        return [definition(parse_arch(a, names)[0]).locals for a in archs]
    except ValueError:
        return None


def check_lags(late: LateModel, arrive: np.ndarray, first: int, K1: int) -> None:
    """ValueError naming the sensor where a reading of the rows from instant `first` arrives
    (instant indices `arrive` (w, S), K1: never) at a lag outside its latency range."""
    for j, lj in enumerate(late.lags):  # the readings' own lags among the model's
        i = np.flatnonzero(arrive[:, j] < K1)
        if not np.isin(arrive[i, j] - (i + first), lj).all():
            name = late.system.sensors[j].name
            raise ValueError(f"sensor {name}: a reading arrives outside its latency range")


class _Stacked(ReplayBlocks):
    """`ReplayBlocks` of the stacked model of one architecture, made per block of time from
    the raw system's window (its per-interval F, Q: nothing of the log's length is stacked)."""

    late: LateModel
    centre: tuple | None
    #: `latency_apart.selection` where correlated readings arrive apart at the plain stacked
    #: model's filters (HKF, the per-sensor locals), else None
    apart: np.ndarray | None = None
    #: the raw R (w, m, m) of the instants of the block `window_system` made last, where each
    #: message carries its own (None: one R)
    raw_Rs: np.ndarray | None = None

    def replay(self, system: System, z: np.ndarray, backward) -> _Replay:
        if self.apart is None:
            return super().replay(system, z, backward)
        r = ApartReplay(system, z, self.need, self.criterion, self.carried, backward)
        r.sel, r.W = self.apart, self.late.window
        # the joint R of each instant the noises enter at: one, or each message's own
        r.raw_R = self.late.system.R if self.raw_Rs is None else self.raw_Rs
        return r

    def window_system(self, k0: int, k1: int, into_first: bool) -> System:
        raw = self.late.system
        if raw.Fs is None and raw.Qs is None:
            stacked = self.system  # one F, Q: the stacked model made once
        else:
            stacked = stacked_system(system_window(raw, k0, k1, into_first), self.late.lags)
            if self.centre is not None:
                cond, lags, slots = self.centre[3], self.late.lags, self.late.slots
                stacked = with_conditions(stacked, cond, lags, slots)[0]
        if raw.Rs is None:
            return stacked
        # each reading's own R: the slots of lag l read the R of instant k - l, so the raw R
        # of the W instants before the block too (`stacked_noise`; no centre here, `of`)
        a = max(0, k0 - self.late.window)
        Rs = np.asarray(raw.Rs[a:k1])
        self.raw_Rs = Rs[k0 - a :]  # the block's own, for the raw noises kept (`replay`)
        return dataclasses.replace(
            stacked, Rs=stacked_noise(Rs, raw.R, self.late.slots, None, k0 - a)
        )


@dataclasses.dataclass
class _Window:
    """The raw readings (rows, m) (NaN: missing) and arrival times (rows, S) s of the last W
    instants before the next block of time."""

    z: np.ndarray
    arrival: np.ndarray


class LateBlocks:
    """The architectures `archs` of one run with late sensors, block of time by block, in
    order (`estimates`, `error_covariances`). `LateBlocks.of` says whether the path takes
    them."""

    def __init__(self, late: LateModel, archs: Sequence[str], inner: dict, times: np.ndarray):
        self.late, self.archs, self.inner, self.times = late, list(archs), inner, times
        self.W = late.window
        S = len(late.system.sensors)
        self.window = _Window(np.zeros((0, late.system.m)), np.zeros((0, S)))
        self.next_instant = 0
        lat = np.array([s.timing.latency for s in late.system.sensors])
        self.fixed = lat[:, 0]  # the fixed latencies (random delays come with the readings)

    @classmethod
    def of(
        cls,
        system: System,
        archs: Sequence[str],
        steps: int,
        times: np.ndarray,
        block: int,
        criterion: str | None = None,
        missing: bool = True,
    ) -> LateBlocks | None:
        """The blocked late path of one run of instants 0..`steps` at `times` (s), the lags found
        in blocks of `block` instants; None where it does not apply (module docstring;
        `missing`: some reading is missing -- with fixed latencies on a steady model and every
        reading present the steady plans do it). Where correlated readings of one instant may
        arrive apart, HKF (which fuses them as independent) and the per-sensor locals (which
        they enter at different instants) have errors correlated across instants: their error
        recursions keep the raw noises still to be read (`core.latency_apart`)."""
        if not cls.covers(system, archs):
            return None
        if not random_delays(system) and system.time_invariant and not missing:
            return None
        times = np.asarray(times, dtype=float)
        late = late_model(system, steps, times, block, conditions=True)
        inner = {}
        for a in archs:
            base, kind, filters = late.filters_of(a)
            if kind not in _KINDS:
                return None
            apart = bool(apart_pairs(system)) and kind in ("hierarchical", "per-sensor")
            centre = late.centre_model() if kind == "centralised" else None
            if system.Rs is not None and centre is not None:
                # correlated readings of one instant arriving apart at the centre, each
                # message with its own R: the decorrelated readings z_j - A z_E have
                # A = R_jE R_EE^-1 of each instant's R, so the stacked filter on fixed
                # coefficients is not the Kalman filter of the arrived readings (its P, which
                # the exact analysis here reads, is not its error covariance): the whole run's
                # plans, an affine map analysed exactly with each instant's R (`latency`)
                return None
            model = late.stacked if centre is None else centre[0]
            m, N, S = model.m, model.n, len(model.sensors)
            per_instant = (2 * S + 2) * m * (m + N) * 8
            if kind in ("per-sensor", "hierarchical"):  # eq. (35)'s J, HKF's E, A and C
                d = S * N if kind == "per-sensor" else N
                d += late.window * system.m if apart else 0  # the raw noises kept
                per_instant += 4 * d * d * 8
            sub = max(1, min(block, LATE_BLOCK_BYTES // per_instant))
            got = _Stacked.of(model, [a], steps, sub, criterion)
            if got is None:
                return None
            if kind == "per-sensor":  # the rule fuses the locals' current blocks
                got.bases = [(current_block_rule(base, system.n, N), None)]
            got.late, got.centre = late, centre
            got.apart = selection(late.slots, system.m, late.window) if apart else None
            inner[a] = (got, filters, centre, sub)
        return cls(late, archs, inner, times)

    @staticmethod
    def covers(system: System, archs: Sequence[str]) -> bool:
        """Whether the path may take `archs` on `system` at all (before any reading is seen):
        late sensors of a linear model with a prior, reprocess or neglect, and filters fusing
        every sensor or one, or the per-sensor rules (`_KINDS`)."""
        kinds = late_kinds(system, archs, retrodict=False)
        return kinds is not None and all(k in _KINDS for k in kinds)

    def _arrivals(self, k0: int, k1: int, arrival: np.ndarray | None) -> np.ndarray:
        """The arrival times (w, S) s of the block's readings: `arrival` (NaN: none taken),
        else the fixed latencies'."""
        if arrival is not None:
            return np.asarray(arrival, dtype=float)
        return self.times[k0:k1, None] + self.fixed[None, :]

    def _masks(self, k0: int, k1: int, z: np.ndarray, arrival: np.ndarray | None):
        """{arch: (stacked readings (w, m~), their presence (w, m~))} of the block [k0, k1)
        laid out on the window [k0 - W, k1), and the window kept for the next block."""
        if k0 != self.next_instant:
            raise ValueError(f"blocks of time in order: {k0} after {self.next_instant}")
        late = self.late
        zw = np.concatenate([self.window.z, z])
        aw = np.concatenate([self.window.arrival, self._arrivals(k0, k1, arrival)])
        s = k0 - len(self.window.z)
        arrive = arrival_steps(self.times, aw)  # the log's instant indices
        check_lags(late, arrive, s, len(self.times))
        present = ~np.isnan(zw)
        out = {}
        for a in self.archs:
            _, filters, centre, _ = self.inner[a]
            mask = late.stacked_mask(present, filters, arrive - s, centre)[k0 - s :]
            slots, coef = (late.slots, None) if centre is None else centre[1:3]
            zs = stacked_readings(zw, slots, coef)[k0 - s :]
            out[a] = (np.where(mask, zs, np.nan), mask)
        keep = max(0, len(zw) - self.W)
        self.window = _Window(zw[keep:].copy(), aw[keep:].copy())
        self.next_instant = k1
        return out

    def _sub_blocks(self, a: str, k0: int, k1: int, rows: np.ndarray, what) -> list:
        """what(inner blocks, b0, b1, the rows of [b0, b1)) of each sub-block of [k0, k1) of
        architecture `a`'s stacked filters (`LATE_BLOCK_BYTES`), in order."""
        blocks, _, _, sub = self.inner[a]
        spans = [(b0, min(b0 + sub, k1)) for b0 in range(k0, k1, sub)]
        return [what(blocks, b0, b1, rows[b0 - k0 : b1 - k0]) for b0, b1 in spans]

    def estimates(
        self, k0: int, k1: int, z: np.ndarray, arrival: np.ndarray | None = None
    ) -> dict[str, Estimate]:
        """Each architecture's estimate (mean (1, w, n), cov (w, n, n)) at the instants
        k0..k1-1 from their readings z (w, m) (NaN: missing) and `arrival` (w, S) s (None: the
        fixed latencies'), the state and readings carried from the block before."""
        n = self.late.system.n
        out = {}
        for a, (zs, _) in self._masks(k0, k1, z, arrival).items():
            got = self._sub_blocks(a, k0, k1, zs, lambda b, b0, b1, r: b.estimates(b0, b1, r, None))
            mean = np.concatenate([e[a].mean[..., :n] for e in got], axis=1)
            out[a] = Estimate(mean, np.concatenate([e[a].cov[..., :n, :n] for e in got]))
        return out

    def error_covariances(
        self, k0: int, k1: int, present: np.ndarray, arrival: np.ndarray | None = None
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each architecture's true error covariance and reported covariance (w, n, n) at the
        instants k0..k1-1 under the model, `present` (w, m) the readings taken there and
        `arrival` (w, S) their arrival times (None: the fixed latencies')."""
        n = self.late.system.n
        z = np.where(present, 0.0, np.nan)
        out = {}
        for a, (_, mask) in self._masks(k0, k1, z, arrival).items():
            got = self._sub_blocks(
                a, k0, k1, mask, lambda b, b0, b1, r: b.error_covariances(b0, b1, r)
            )
            out[a] = tuple(np.concatenate([g[a][i][:, :n, :n] for g in got]) for i in (0, 1))
        return out
