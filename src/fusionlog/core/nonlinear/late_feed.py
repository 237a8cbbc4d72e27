"""The readings of the EKF/UKF lanes' late policies (`late`, `retrodict`), instant by instant:
what the output instant k may use is the readings of the instants k-W..k with the instant each
arrives at (DESIGN.md "Late measurements"), so the policies hold those W + 1 instants, not the
log (issue 34: a long one-run log in blocks of time, `long_log.estimate_blocks`).

`Feed` reads the readings a block at a time (`read(k0, k1)`: (M, w, m)) with their arrival
instants (`arrivals(k0, k1)`: (M or 1, w, S), K+1 for never), keeps the last W instants of
the block before beside the block, and decides neglect's rule (`late_policy.accepted`) for
the readings that arrive at k when k is reached: a reading is taken or dropped at its arrival,
from the filter's newest measurement time so far, which is `accepted`'s recursion carried.
The whole run is one block of the same feed, so a log in blocks runs the same operations.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from ...errors import FusionlogError
from ..late_policy import accept_at, arrival_steps, random_delays
from ..model import System

__all__ = ["Feed", "arrival_instants", "fixed_arrivals", "window_of"]

#: (k0, k1) -> an array of the instants k0..k1-1 (readings (M, w, m) or arrivals (M, w, S)).
Reader = Callable[[int, int], np.ndarray]


def arrival_instants(system: System, times: np.ndarray, arrival: np.ndarray | None) -> np.ndarray:
    """The instant index at which each reading arrives, (runs or 1, K+1, S) (K+1: never,
    within the horizon): from `arrival` (runs, K+1, S) seconds on the clock of `times`, or
    where it is None from the sensors' fixed latencies."""
    times = np.asarray(times, float)
    if arrival is None:
        if random_delays(system):
            raise FusionlogError(
                "arrival: a sensor's latency is a range (random delays): give the arrival "
                "times of the readings (runs, K+1, S) s"
            )
        lat = np.array([s.timing.latency[0] for s in system.sensors])
        arrival = (times[:, None] + lat[None, :])[None]
    arrival = np.asarray(arrival, float)
    S, K1 = len(system.sensors), len(times)
    if arrival.ndim != 3 or arrival.shape[1:] != (K1, S):
        raise FusionlogError(
            f"arrival: shape {arrival.shape}, expected (runs, {K1}, {S}): when each reading "
            "of each sensor arrived (s)"
        )
    return _instants(times, arrival, 0)


def fixed_arrivals(
    system: System, times: np.ndarray, arrival: np.ndarray | Reader | None
) -> Reader:
    """The arrival instants of the readings of k0..k1-1, (runs or 1, w, S): from `arrival`
    (runs, K+1, S) s (checked and taken whole, as the log gives them), or a block of time at a
    time from `arrival(k0, k1)` ((runs or 1, w, S) s: a long log's, read per block, issue 34),
    or where it is None the sensors' fixed latencies on the clock `times`
    (`arrival_instants`' numbers, a block at a time)."""
    times = np.asarray(times, float)
    if callable(arrival):
        return lambda k0, k1: _instants(times, arrival(k0, k1), k0)
    if arrival is not None:
        got = arrival_instants(system, times, arrival)
        return lambda k0, k1: got[:, k0:k1]
    lat = np.array([s.timing.latency[0] for s in system.sensors])
    return lambda k0, k1: arrival_steps(times, (times[k0:k1, None] + lat[None, :])[None])


def _instants(times: np.ndarray, arrival: np.ndarray, k0: int) -> np.ndarray:
    """`arrival_instants` of the block of arrivals (runs, w, S) s of the instants k0.. ."""
    if (arrival < times[None, k0 : k0 + arrival.shape[1], None] - 1e-9).any():
        raise FusionlogError("arrival: a reading arrives before it is taken")
    return arrival_steps(times, arrival)


def _masked(z: np.ndarray, arrive: np.ndarray, cols: list, used: np.ndarray, K1: int):
    """`arrive` where the sensor took the reading and a filter fuses it, else K+1 (never)."""
    took = np.stack([~np.isnan(z[:, :, c]).all(-1) for c in cols], axis=-1)
    arrive = np.broadcast_to(arrive, took.shape)
    return np.where(took & used, arrive, K1)


def window_of(
    read: Reader, arrivals: Reader, cols: list, used: np.ndarray, K1: int, block: int
) -> int:
    """W: the largest lag (in instants) of a reading taken and fused that arrives within the
    horizon (`late.window` over the whole log), read a block at a time."""
    W = 0
    for k0 in range(0, K1, block):
        k1 = min(k0 + block, K1)
        a = _masked(read(k0, k1), arrivals(k0, k1), cols, used, K1)
        lag = np.where(a < K1, a - np.arange(k0, k1)[:, None], 0)
        W = max(W, int(lag.max(initial=0)))
    return W


class Feed:
    """The readings z_i (M, m) and arrival instants (M, S) of the instants k-W..k (`at`), after
    `advance(k)`; `neglect`: the sensors each filter fuses, whose readings older than its last
    update are dropped as they arrive (None: every reading is taken)."""

    def __init__(
        self,
        read: Reader,
        arrivals: Reader,
        M: int,
        K1: int,
        cols: list,
        used: np.ndarray,
        W: int,
        block: int,
        neglect: list[list[int]] | None = None,
    ) -> None:
        self.read, self.arrivals, self.M, self.K1 = read, arrivals, M, K1
        self.cols, self.used, self.W, self.block = cols, used, W, block
        self.groups = neglect
        self.newest = [np.full(M, -1, dtype=np.intp) for _ in neglect or ()]
        self.base, self.end = 0, 0  # the instants held: base..end-1
        self.z = np.zeros((M, 0, sum(len(c) for c in cols)))
        self.arrive = np.zeros((M, 0, len(cols)), dtype=np.intp)

    def advance(self, k: int) -> None:
        """Hold instant k (reading the block it starts), and decide neglect's rule for the
        readings that arrive at k."""
        if k >= self.end:
            k1 = min(k + self.block, self.K1)
            z = self.read(k, k1)
            a = _masked(z, self.arrivals(k, k1), self.cols, self.used, self.K1)
            keep = max(0, min(self.W, self.end - self.base))  # the window before the block
            self.z = np.concatenate([self.z[:, self.z.shape[1] - keep :], z], axis=1)
            self.arrive = np.concatenate([self.arrive[:, self.arrive.shape[1] - keep :], a], 1)
            self.base, self.end = k - keep, k1
        if self.groups is not None:
            self._neglect(k)

    def _neglect(self, k: int) -> None:
        """`late_policy.accepted` at instant k, per filter: of the readings arriving at k
        those older than the newest measurement time it has taken are dropped (never)."""
        lo = max(0, k - self.W)
        i = np.arange(lo, k + 1)
        rows = self.arrive[:, lo - self.base : k + 1 - self.base]  # a view: changed in place
        for f, g in enumerate(self.groups):
            here = rows[..., g] == k
            ok, self.newest[f] = accept_at(here, i, self.newest[f])
            rows[..., g] = np.where(here & ~ok, self.K1, rows[..., g])

    def z_at(self, i: int) -> np.ndarray:
        """(M, m) the readings taken at instant i (k-W <= i <= k)."""
        return self.z[:, i - self.base]

    def arrive_at(self, lo: int, hi: int) -> np.ndarray:
        """(M, hi-lo, S) the arrival instants of the readings of lo..hi-1."""
        return self.arrive[:, lo - self.base : hi - self.base]


def driven(feed: Feed, inner: Iterator) -> Iterator:
    """`inner`'s estimates, instant k's after the feed holds it."""
    for k in range(feed.K1):
        feed.advance(k)
        yield next(inner)
