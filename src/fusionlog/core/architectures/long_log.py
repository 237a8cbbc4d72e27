"""A long one-run log in blocks of time, in memory that does not grow with its instants (issue
34): the plans of a short horizon standing for the whole log, their recursions carried from
block to block.

With a time-invariant model and every measurement present, every plan reaches its steady
state (`filters.Steady`: the covariance recursion repeats to 1e-15) after a transient: from
then on each step's maps are the same `StepMap` object. The smoother's backward maps are
steady too, except over a transient before the log's end. So a plan built over a horizon of
H instants, whose middle step c is steady, *is* the plan of any longer log K + 1 > H with its
steps indexed by `SteadyLog.index`: k for k < c, the same distance from the end for the last
H - c instants, c in between -- the maps the full plan would repeat (eqs. 14-18 forward, HKF
36-40, the fusions 6-7, 32-35, FBS 25-28 backward), and, converged to rounding, the exact
analysis of Section IV (eq. 35's joint covariance propagated through them: `expected`).

The estimates of a block [k0, k1) follow from each architecture's internal state s_{k0-1}
(carried) and the block's measurements. FBS's backward information vector y_b[k] of eq. (25)
needs the measurements after k: `backward` runs it over the blocks in reverse order, carrying
y_b and z of the block after, and the caller keeps what it gives (on disk) for the forward
pass, which fuses it with the forward filter's states block by block (eq. 28).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..expected import Expected
from ..model import System
from .executor import STEADY_BLOCK, _recursion, _steady_states
from .plan import Plan, StepMap
from .registry import build_plan

__all__ = ["HORIZONS", "SteadyLog", "steady_log"]

#: Instants of the plans that stand for a long log, tried in turn until their middle is
#: steady (a 200 Hz constant-velocity log takes ~1500 instants to reach its steady state).
#: The steady maps are one object each: a longer horizon costs its transient, not its length.
HORIZONS = (4096, 16384, 65536)


@dataclass
class SteadyLog:
    """The plans (`plans`, over `horizon` instants, middle step `c` steady) of a log of
    `steps` + 1 instants, and each architecture's state carried from block to block."""

    plans: dict[str, Plan]
    steps: int
    horizon: int
    state: dict[str, np.ndarray] = field(default_factory=dict)  # s_{k0-1}, (1, d)
    _forward: dict[int, StepMap] = field(default_factory=dict, repr=False)
    _mapped: dict[str, list[StepMap]] = field(default_factory=dict, repr=False)

    @property
    def c(self) -> int:
        return self.horizon // 2

    @property
    def whole(self) -> bool:
        """The plans are over the whole log (`index` is k itself)."""
        return self.horizon == self.steps + 1

    def index(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0,) the plans' step standing for each instant k0..k1-1."""
        k = np.arange(k0, k1)
        H, K, c = self.horizon, self.steps, self.c
        out = np.full(k.shape, c)
        out[k < c] = k[k < c]
        end = K - k < H - c
        out[end] = H - 1 - (K - k[end])
        return out

    def first_instant(self, h: int) -> int:
        """The first instant whose plan step is `h` (`index`'s inverse)."""
        if h <= self.c or self.whole:
            return h
        return self.steps - (self.horizon - 1 - h)

    def cov(self, arch: str, k0: int, k1: int) -> np.ndarray:
        """(w, n, n): the covariance `arch` reports at the instants k0..k1-1."""
        plan = self.plans[arch]
        P = plan.smoother.P if plan.smoother is not None else [st.P for st in plan.steps]
        return _gather(P, self.index(k0, k1))

    def expected(self, arch: str, truth: System) -> Expected:
        """The exact analysis of the short plan (`exact.analyse`), whose steps `index` maps."""
        from ..exact import analyse

        return analyse(self.plans[arch], truth)

    def forward(self, arch: str, z: np.ndarray, k0: int, yb: np.ndarray | None) -> np.ndarray:
        """The means (1, w, n) of `arch` at the instants k0..k0+w-1 from the block's z (1, w, m)
        and the carried state; FBS takes the block's backward vectors `yb` (w, n)."""
        plan = self.plans[arch]
        idx = self.index(k0, k0 + z.shape[1])
        s0 = self.state[arch][0] if arch in self.state else plan.s0
        sm = plan.smoother
        # the block's maps: the steady ones stay one object (the executor's steady blocks);
        # FBS: its forward filter's states themselves (O = I), fused below
        base = plan.steps
        if sm is not None:
            if arch not in self._mapped:
                self._mapped[arch] = [self._states_map(st) for st in plan.steps]
            base = self._mapped[arch]
        steps, steady = _picked(base, idx, self.c)
        last: list = []
        with np.errstate(over="ignore", invalid="ignore"):
            out = _recursion(_Block(plan.name, s0, steps, steady_at=steady), z, s0, last=last)
        self.state[arch] = last[0]
        if sm is None:
            return out
        mean = np.empty((1, len(idx), sm.A[0].shape[-2]))
        for a, b, i in _runs(idx):  # eq. (28), x_s = A s_f + B y_b, a run of one map at once
            mean[0, a:b] = out[0, a:b] @ sm.A[i].T + yb[a:b] @ sm.B[i].T
        return mean

    def _states_map(self, st: StepMap) -> StepMap:
        """`st` with O = I (its output is the state), one object per object of the plan."""
        key = id(st)
        got = self._forward.get(key)
        if got is None:
            got = self._forward[key] = StepMap(st.T, st.U, np.eye(st.T.shape[-2]), st.P, st.D)
        return got

    def backward(
        self, arch: str, z: np.ndarray, k0: int, carried: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """FBS's backward information vectors y_b (w, n) at k0..k0+w-1, eq. (25): y_b[K] = 0,
        y_b[k] = L_k (y_b[k+1] + V_{k+1} z_{k+1}), from the block's z (1, w, m) and `carried`
        (y_b and z (m,) of the instant after the block; None for the log's last block).
        Returns them and what the block before carries."""
        sm = self.plans[arch].smoother
        w = z.shape[1]
        idx = self.index(k0, k0 + w + 1)  # and the instant after the block
        zz = np.where(np.isnan(z[0]), 0.0, z[0])
        n = sm.B[0].shape[-1]
        out = np.empty((w, n))
        zfull = np.concatenate([zz, np.zeros((1, zz.shape[1]))])  # z of the instant after
        if carried is None:  # the log's last instant: no information from after it
            y, k = np.zeros(n), w - 2
            out[w - 1] = y
        else:
            y, zfull[w] = carried
            k = w - 1
        # where L and V are the steady map c (step and the next): run there in blocks
        breaks = np.flatnonzero(~((idx[:-1] == self.c) & (idx[1:] == self.c)))
        while k >= 0:
            at = int(np.searchsorted(breaks, k, side="right"))
            start = int(breaks[at - 1]) + 1 if at else 0  # first of the steady stretch
            N = (k + 1 - start) // STEADY_BLOCK * STEADY_BLOCK
            if N >= 2 * STEADY_BLOCK:
                # y_k = L y_{k+1} + L V z_{k+1}: the forward recursion of z_{k+1}, z_k, ...
                Lm = sm.L[self.c]
                inputs = zfull[k - N + 2 : k + 2][::-1]
                Y = _steady_states(Lm, Lm @ sm.V[self.c], y[None], inputs[None])[0]
                out[k - N + 1 : k + 1] = Y[::-1]
                y, k = Y[-1], k - N
                continue
            y = sm.L[idx[k]] @ (y + sm.V[idx[k + 1]] @ zfull[k + 1])
            out[k] = y
            k -= 1
        return out, (out[0].copy(), zz[0].copy())


@dataclass
class _Block(Plan):
    """A block's plan (`SteadyLog.forward`) whose steady tail is known from how its steps were
    picked (`_picked`), not found by comparing each of its 65 536 steps."""

    steady_at: int = 0

    @property
    def steady_from(self) -> int:
        return self.steady_at


def _picked(base: list[StepMap], idx: np.ndarray, c: int) -> tuple[list[StepMap], int]:
    """[base[i] for i in idx] for `SteadyLog.index`'s steps (consecutive below c, c, then
    consecutive again), made of slices and one repeated object, and where the trailing run of
    the last map starts (`Plan.steady_from`), found without visiting the repeated middle."""
    lo, hi = (int(x) for x in np.searchsorted(idx, [c, c + 1]))
    head = base[int(idx[0]) : int(idx[0]) + lo] if lo else []
    tail = base[int(idx[hi]) : int(idx[hi]) + len(idx) - hi] if hi < len(idx) else []
    mid = [base[c]] * (hi - lo)
    steps = head + mid + tail
    last = steps[-1]
    j = len(tail)
    while j > 0 and tail[j - 1] is last:
        j -= 1
    if j > 0 or (mid and mid[0] is not last):
        return steps, lo + len(mid) + j
    j = lo
    while j > 0 and head[j - 1] is last:
        j -= 1
    return steps, j


def _runs(idx: np.ndarray):
    """(a, b, i): the stretches [a, b) of equal `idx`, i their index."""
    cut = np.flatnonzero(np.diff(idx)) + 1
    edges = [0, *cut.tolist(), len(idx)]
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        yield a, b, int(idx[a])


def _gather(mats: Sequence[np.ndarray], idx: np.ndarray) -> np.ndarray:
    """mats[idx] as one (w, ...) array, each stretch of one map a broadcast copy."""
    out = np.empty((len(idx), *mats[0].shape))
    for a, b, i in _runs(idx):
        out[a:b] = mats[i]
    return out


def _steady(plan: Plan, c: int) -> bool:
    """Whether the plan's step c and its neighbours are one steady map (forward and, for the
    smoother, backward and fusion), and the forward maps stay it to the horizon's end."""
    st = plan.steps
    if not (st[c - 1] is st[c] and st[c] is st[-1]):
        return False
    sm = plan.smoother
    if sm is None:
        return True
    return all(
        lst[c - 1] is lst[c] and lst[c] is lst[c + 1] for lst in (sm.L, sm.A, sm.B, sm.P, sm.V)
    )


def steady_log(
    system: System,
    archs: Sequence[str],
    steps: int,
    criterion: str = "trace",
    build: Callable[[str, int], Plan] | None = None,
) -> SteadyLog | None:
    """The short plans standing for a log of instants 0..`steps` with every measurement present
    (`SteadyLog`), or None where they do not: a model that is not time-invariant or linear, or
    plans not steady by the middle of the longest horizon (`HORIZONS`). A log no longer than
    that horizon has its plans over all of it (`SteadyLog.whole`). `build(arch, K)`: the plan
    of instants 0..K (default `build_plan`; late sensors: `core.latency_long`)."""
    if not (system.linear and system.time_invariant):
        return None
    if build is None:

        def build(arch: str, K: int) -> Plan:
            return build_plan(system, arch, K, None, criterion)

    if steps + 1 <= HORIZONS[-1]:
        plans = {a: build(a, steps) for a in archs}
        return SteadyLog(plans, steps, steps + 1)
    for horizon in HORIZONS:
        plans = {a: build(a, horizon - 1) for a in archs}
        if all(_steady(p, horizon // 2) for p in plans.values()):
            return SteadyLog(plans, steps, horizon)
    return None


def expected_window(ex: Expected, idx: np.ndarray) -> Expected:
    """The exact values of a short plan's analysis at the steps `idx` (`SteadyLog.index`)."""
    return Expected(*(getattr(ex, f)[idx] for f in ("mse", "bias", "P", "nees", "dm")))


def converged(ex: Expected, c: int, rtol: float = 1e-9) -> bool:
    """Whether the analysis has reached its steady value at the middle step c (the error
    covariance's recursion converges more slowly than the filter's, which `Steady` checks)."""
    a, b, d = ex.mse[c - 1], ex.mse[c], ex.mse[c + 1]
    scale = np.abs(b).max()
    return bool(np.abs(a - b).max() <= rtol * scale and np.abs(d - b).max() <= rtol * scale)
