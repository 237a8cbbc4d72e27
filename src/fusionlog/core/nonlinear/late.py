"""Late measurements in the EKF/UKF lanes (DESIGN.md "Late measurements"), every run of a
block at once (arrays over the runs; each run its own arrivals where the delays are random).

An architecture is a recursion on its state, s_k = step(k, s_{k-1}, z_k), its estimate
out(s_k) (`architectures.Machine`: the CKF's or SKF's filter, HKF's centre, the track-to-track
locals with their joint covariance). At the output instant t_k only the readings that have
arrived by then (arrival <= t_k) may be used:

* *reprocess*: the states of the last W + 1 instants are kept (W the largest lag in instants:
  the bounded history, W + 1 states of the architecture per run). When readings taken at
  t_i, i < k, arrive at k, each run rewinds to its oldest newly arrived reading's instant i0
  and reruns `step` from its stored state at i0 - 1 to k with every reading of those instants
  that has arrived. The rerun *relinearises*: the EKF's Jacobians (the UKF's sigma points) are
  taken afresh at the refiltered estimates, so the state kept at instant i is exactly the
  filter run from scratch on the readings taken by t_i that have arrived by t_k (a run whose
  own i0 is later keeps its stored states: the rerun starts at the block's oldest i0).
* *neglect*: a reading older than the last update of the filter that fuses it (the newest
  measurement time it has taken; `core.late_policy.accepted`, per local filter in the track-to-
  track architectures) is dropped, the others processed as reprocess does. As they are not
  older than the last update, the rewind goes back to that update at most: between it and
  t_k the stored states are predictions, so this is the event-driven filter that predicts
  from its last update to each accepted reading (a reading of the last update's own instant
  that arrives later is fused with that instant's others, the update of that instant redone).
* *retrodict*: `retrodict` (Bar-Shalom's Al1 with the EKF's Jacobians, in each filter that
  fuses the late sensor: the one filter, HKF's centre, each track-to-track local).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .late_feed import Feed, Reader, arrival_instants, driven, window_of
from .local import select

__all__ = ["arrival_instants", "late_steps", "reprocess_steps"]


def late_steps(
    m, filters: list[list[int]], arrive, read: Reader | None = None, block: int = 0
) -> Iterator:
    """The estimates (x, P) at each output instant of machine `m` (its system's policy,
    `System.late`) with the readings arriving at the instants `arrive` (runs or 1, K+1, S);
    `filters`: the sensors each of its filters fuses (neglect's last update is per filter).
    A long log (`long_log.estimate_blocks`): `arrive` and `read` give the arrival instants
    and the readings of instants k0..k1-1, read `block` instants at a time (`late_feed`)."""
    st = m.st
    K1 = len(st.times)
    if read is None:  # the whole run: one block of the arrays
        z, a = st.z, arrive
        read, arrive, block = (lambda k0, k1: z[:, k0:k1]), (lambda k0, k1: a[:, k0:k1]), K1
    S = len(st.system.sensors)
    used = np.isin(np.arange(S), [j for g in filters for j in g])
    W = window_of(read, arrive, st.cols, used, K1, block)
    policy = st.system.late
    neglect = filters if policy == "neglect" else None
    feed = Feed(read, arrive, st.z.shape[0], K1, st.cols, used, W, block, neglect)
    if policy == "retrodict":
        from .retrodict import retrodict_steps

        return driven(feed, retrodict_steps(m, feed))
    return driven(feed, reprocess_steps(m, feed))


def reprocess_steps(m, feed: Feed) -> Iterator:
    """Reprocessing (module docstring): machine `m` rerun from each run's stored state before
    its oldest newly arrived reading, the readings and their arrival instants (K+1: never) of
    the last W + 1 instants from `feed` (W the largest lag)."""
    st = m.st
    col_sensor = np.concatenate([np.full(len(c), j) for j, c in enumerate(st.cols)])
    W = feed.W
    steps = np.arange(feed.K1)
    hist = {-1: m.start()}  # the state after instant i, with what has arrived so far
    for k in range(feed.K1):
        lo = max(0, k - W)
        new = (feed.arrive_at(lo, k + 1) == k).any(-1)  # (M, k+1-lo): a reading of i arrives
        i0 = np.where(new.any(-1), steps[lo : k + 1][np.argmax(new, -1)], k)
        s = hist[int(i0.min()) - 1]
        for i in range(int(i0.min()), k + 1):
            arrived = feed.arrive_at(i, i + 1)[:, 0, col_sensor] <= k  # (M, m)
            zi = np.where(arrived, feed.z_at(i), np.nan)
            s = m.step(i, s, zi)
            if i < k:  # runs whose rewind starts later keep their stored state
                s = select(i >= i0, s, hist[i])
            hist[i] = s
        for i in [i for i in hist if i < k - W]:
            del hist[i]
        yield m.out(s)
