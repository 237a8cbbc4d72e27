"""Retrodiction (``late = "retrodict"``) of a long one-run log in blocks of time (issue 34),
where no short steady plans stand for the log (`core.latency_long`): delays drawn per reading
or recorded (a replay's ``arrival = "log_time"``), readings missing, and the rules that read
J where the error form is 0 (a transition over the window singular or ill-conditioned: J then
carries the truth's growing covariance and never repeats, so there is no steady middle).

Design: the plans of each block carried from the block before. Bar-Shalom's Al1 (2002, 2004;
`core.retrodict`) needs a bounded history -- the estimate of its last update, the estimates
stored over the latency window W and the readings of the last W instants -- and the plan's
state s_k = [cur; stored estimates of k-W..k; z_{k-W+1}..z_k] holds exactly that. The gains
depend on the arrivals only, and their recursion's state is as bounded: each filter's P, the
instant of its last update and the covariances of the stored estimates (`retrodict.Recursion`),
the rules' J through cov([x_k; s_k - D_k x_k]) (`retrodict_fused.FusedSteps`). So a block
[k0, k1) is planned from the recursions carried to k0 and the presence and arrivals of the W
instants before it (`_Window`), and run from the state s_{k0-1} carried; the exact analysis
carries the joint moments of [x_k; s_k - D_k x_k] (`moments.step_moments`) the same way. The
maps are the whole run's (the same code builds them, `late_retrodict_plan`), so blocked = whole
to rounding, and nothing needs to repeat: it also takes J where D = 0.

Why not the plan-free path of `core.latency_blocks` (reprocess, neglect): that path is a
Kalman filter on a stacked model whose reported covariance is its error covariance. Al1 over
several updates is an approximation: its reported covariance is not its error covariance, and
the rules read the locals' true J, so the exact analysis and J need the affine maps anyway --
with the maps at hand, running them is the filter itself. A block is cut into sub-blocks so
that the maps held stay below `RETRO_BLOCK_BYTES`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .architectures import Plan, StepMap
from .architectures.hkf import independent_noise
from .architectures.plan import Estimate
from .late_policy import arrival_steps
from .latency import LateModel
from .latency_blocks import check_lags, late_kinds, late_model
from .linalg import sym
from .model import System
from .moments import congruences, hcat, initial_moments, mv, step_moments
from .retrodict import Recursion, Transitions, initial_state
from .retrodict_fused import FusedSteps

__all__ = ["RETRO_BLOCK_BYTES", "RetroBlocks"]

#: The maps a sub-block of one architecture may hold (bytes).
RETRO_BLOCK_BYTES = 1 << 24


@dataclasses.dataclass
class _Window:
    """Presence (rows, m) and arrival instants (rows, S) of the last W instants before the next
    block of time."""

    present: np.ndarray
    arrive: np.ndarray


class _Filter:
    """One architecture's retrodicting filters, block by block: its gain recursions (one filter
    or a centre, or a local per sensor and the rule), its state s_{k0-1} and, for the exact
    analysis, the moments of [x; s - D x] carried."""

    def __init__(self, system: System, late: LateModel, arch: str, criterion: str) -> None:
        base, kind, filters = late.filters_of(arch)
        M = 1
        self.trans = Transitions(system)
        if kind == "per-sensor":
            Ws = [int(lj.max()) for lj in late.lags]
            self.locals = [Recursion(system, [j], Ws[j], M, self.trans) for j in range(len(Ws))]
            self.fuser: FusedSteps | None = FusedSteps(system, base, Ws, criterion)
            self.s0, self.D0 = self.fuser.s0, self.fuser.D0
        else:
            W = max(int(late.lags[j].max()) for j in filters[0])
            own = independent_noise(system) if kind == "hierarchical" else system
            own_trans = self.trans if own is system else Transitions(own)
            self.locals = [Recursion(own, filters[0], W, M, own_trans)]
            self.fuser = None
            self.s0, self.D0 = initial_state(system, W)
        self.name = arch
        self.s = self.s0[None]  # (1, d)
        self.moments: tuple | None = None  # (mu, C, D_prev) of the exact analysis

    def maps(self, present: np.ndarray, arrive: np.ndarray, k0: int, k1: int, first: int):
        """The steps k0..k1-1 (`StepMap`, shared: the one run's) from the presence (rows, m)
        and arrival instants (rows, S) of the instants first.. (from k0 - W on)."""
        got = [r.steps(present[None], arrive[None], k0, k1, first) for r in self.locals]
        for r in self.locals:  # what a later step asks for: the window's pairs and after
            self._prune(r.trans, k1)
        one = [[tuple(f[0] for f in st) for st in g] for g in got]
        if self.fuser is None:
            return [StepMap(*st) for st in one[0]]
        return self.fuser.steps(one, k0)[0]

    @staticmethod
    def _prune(trans: Transitions, k: int) -> None:
        """Forget the transitions that end before the instants still to come (a bounded cache;
        whatever is asked again is computed again, the same numbers)."""
        if trans.invariant:  # kept by b - a: no more than the gaps between updates
            return
        for cache in (trans.cache, trans.inverses):
            for key in [key for key in cache if key[1] < k - 1]:
                del cache[key]


class RetroBlocks:
    """The architectures `archs` of one run retrodicting its late readings, block of time by
    block, in order (`estimates`, or `error_covariances`: one object for one of them).
    `RetroBlocks.of` says whether the path takes them. Its interface is `latency_blocks.
    LateBlocks`'s (the stages read `late`, `archs` and these two)."""

    def __init__(self, late: LateModel, archs: Sequence[str], times: np.ndarray, criterion: str):
        system = late.system
        self.late, self.archs, self.times = late, list(archs), times
        self.filters = {a: _Filter(system, late, a, criterion) for a in archs}
        self.W = late.window
        S = len(system.sensors)
        self.window = _Window(np.zeros((0, system.m), bool), np.zeros((0, S), np.intp))
        self.next_instant = 0
        lat = np.array([s.timing.latency for s in system.sensors])
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
    ) -> RetroBlocks | None:
        """The blocked retrodiction of one run of instants 0..`steps` at `times` (s), the lags
        found in blocks of `block` instants (`LateBlocks.of`'s signature; every case is taken,
        `missing` changes nothing); None where `covers` says no."""
        del missing
        if not cls.covers(system, archs):
            return None
        times = np.asarray(times, dtype=float)
        late = late_model(system, steps, times, block, conditions=False)
        return cls(late, archs, times, criterion or "trace")

    @staticmethod
    def covers(system: System, archs: Sequence[str]) -> bool:
        """Whether the path takes `archs` on `system`: late sensors of a linear model with a
        prior, retrodicted, by any architecture but the smoother (refused with late sensors)."""
        kinds = late_kinds(system, archs, retrodict=True)
        return kinds is not None and all(k != "smoother" for k in kinds)

    def _arrivals(self, k0: int, k1: int, arrival: np.ndarray | None) -> np.ndarray:
        """The arrival instants (w, S) of the block's readings (`arrival` s, NaN: none taken;
        None: the fixed latencies'), checked against the model's lags."""
        if arrival is None:
            arrival = self.times[k0:k1, None] + self.fixed[None, :]
        arrive = arrival_steps(self.times, np.asarray(arrival, dtype=float))
        check_lags(self.late, arrive, k0, len(self.times))
        return arrive

    def _spans(self, k0: int, k1: int, present: np.ndarray, arrival: np.ndarray | None):
        """(a, b, step maps of [a, b)) of each architecture's sub-blocks of [k0, k1), in order,
        the window [k0 - W, k1) of presence and arrivals laid out once."""
        if k0 != self.next_instant:
            raise ValueError(f"blocks of time in order: {k0} after {self.next_instant}")
        pw = np.concatenate([self.window.present, present])
        aw = np.concatenate([self.window.arrive, self._arrivals(k0, k1, arrival)])
        first = k0 - len(self.window.present)
        keep = max(0, len(pw) - self.W)
        self.window = _Window(pw[keep:].copy(), aw[keep:].copy())
        self.next_instant = k1
        for a, f in self.filters.items():
            d = len(f.s0)
            n, m = self.late.system.n, self.late.system.m
            per_step = 8 * 3 * (d * (d + m + 2 * n) + n * n)  # the maps and their parts
            sub = max(1, RETRO_BLOCK_BYTES // per_step)
            for b0 in range(k0, k1, sub):
                b1 = min(b0 + sub, k1)
                yield a, b0, b1, f.maps(pw, aw, b0, b1, first)

    def estimates(
        self, k0: int, k1: int, z: np.ndarray, arrival: np.ndarray | None = None
    ) -> dict[str, Estimate]:
        """Each architecture's estimate (mean (1, w, n), cov (w, n, n)) at the instants
        k0..k1-1 from their readings z (w, m) (NaN: missing) and `arrival` (w, S) s (None: the
        fixed latencies'), the filters and the readings carried from the block before."""
        n, w = self.late.system.n, k1 - k0
        out = {a: Estimate(np.empty((1, w, n)), np.empty((w, n, n))) for a in self.archs}
        zz = np.where(np.isnan(z), 0.0, z)  # absent: zero gain (and 0 in the kept readings)
        for a, b0, _, steps in self._spans(k0, k1, ~np.isnan(z), arrival):
            f, e = self.filters[a], out[a]
            s = f.s
            with np.errstate(over="ignore", invalid="ignore"):
                for k, st in enumerate(steps, start=b0 - k0):
                    s = s @ st.T.T + zz[k] @ st.U.T
                    e.mean[0, k] = s[0] @ st.O.T
                    e.cov[k] = st.P
            f.s = s
        return out

    def error_covariances(
        self, k0: int, k1: int, present: np.ndarray, arrival: np.ndarray | None = None
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each architecture's true error covariance (its MSE matrix, `exact`'s) and reported
        covariance (w, n, n) at the instants k0..k1-1 under the model (the truth), `present`
        (w, m) the readings taken there and `arrival` (w, S) their arrival times (None: the
        fixed latencies'): the moments of [x_k; s_k - D_k x_k] carried (`moments`)."""
        got = self.mismatch(k0, k1, present, arrival, self.late.system)
        return {a: (mse, P) for a, (mse, _, P) in got.items()}

    def takes(self, truth: System) -> bool:
        """Whether `mismatch` takes the data's model `truth`: linear, of the filters' sizes,
        without a motion model (the moments are the plans' own, `moments.step_moments`)."""
        model = self.late.system
        dims = [s.dim for s in truth.sensors] == [s.dim for s in model.sensors]
        return truth.linear and truth.motion_model is None and truth.n == model.n and dims

    def mismatch(
        self, k0: int, k1: int, present: np.ndarray, arrival: np.ndarray | None, truth: System
    ) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """`error_covariances` where the data come from `truth` (its model, initial
        distribution, noises; `takes`): the MSE matrix, error mean and reported covariance
        (w, ...) of each architecture, the joint moments under `truth` carried."""
        n, w = truth.n, k1 - k0
        Ht = truth.linear_measurement()
        out = {a: (np.empty((w, n, n)), np.empty((w, n)), np.empty((w, n, n))) for a in self.archs}
        for a, b0, _, steps in self._spans(k0, k1, present, arrival):
            f, (mse, mean, P) = self.filters[a], out[a]
            if f.moments is None:
                start = Plan(a, f.s0, [], D0=f.D0)
                mu, C, nx = initial_moments(start, truth)  # nx = n: x's terms kept
                assert nx == n
                f.moments = (mu, C, f.D0)
            mu, C, D_prev = f.moments
            for k, st in enumerate(steps, start=b0):
                mu, C = step_moments(st, k, mu, C, D_prev, truth, n, Ht)
                L = hcat(np.eye(n) - st.O @ st.D, -st.O)  # e = (I - O D) x - O zeta, `exact`
                mean[k - k0] = bias = mv(L, mu)
                mse[k - k0] = sym(congruences([(L, C)])) + np.outer(bias, bias)
                P[k - k0] = st.P
                D_prev = st.D
            f.moments = (mu, C, D_prev)
        return out
