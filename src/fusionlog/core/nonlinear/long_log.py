"""A long one-run log of a nonlinear model (EKF/UKF local filters) estimated in blocks of time
(issue 34), in memory that does not grow with its instants.

The filters (CKF, SKF, HKF and the track-to-track architectures, `.architectures`) are
recursions on their state (`Machine`: s_k = step(k, s_{k-1}, z_k)): each keeps its state from
block to block and takes a block's readings instant by instant, so a block's estimates are
the whole run's. With late sensors each architecture runs its policy (`late.late_steps`) on a
`late_feed.Feed` that reads the log a block at a time and keeps the last W instants' readings
and arrival instants beside it; the policy keeps what else crosses an edge (the states a
reprocess rewinds to, the estimates Al1 retrodicts from, neglect's newest measurement times).

FBS, the extended / unscented RTS smoother, needs the instants after. Its forward filter is
*recomputed*, not written to disk: a first sweep keeps the filter's estimate (x, P) at the end
of each block (the checkpoints, one per block); a reverse sweep recomputes each block's forward
pass from the checkpoint before it and runs the backward pass (`rts`) from the smoothed
estimate at the first instant of the block after, keeping the block's own; handing the blocks
out in order recomputes each once more. Three forward and two backward passes of the CKF, the
readings read back block by block (`read`), one block in memory; the same operations on the
same numbers as the whole run's smoother.

A log whose messages carry their own covariance (`System.Rs`) goes the same way: every update
takes R of its instant (`local.stacked`), in blocks as in the whole run; a long log's Rs is
formed a stretch of instants at a time (`core.intervals.PerInstant`), not held whole.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np

from ..late_policy import is_late
from ..model import System
from .architectures import (
    Machine,
    _filter_machine,
    _named,
    _Out,
    _Steps,
    late_filters,
    machine_of,
    require_filter,
    rts,
)
from .late import late_steps
from .late_feed import fixed_arrivals

__all__ = ["estimate_blocks"]

#: The readings (1, w, m) of the instants k0..k1-1 (NaN: absent).
Reader = Callable[[int, int], np.ndarray]


def estimate_blocks(
    system: System,
    archs: Sequence[str],
    read: Reader,
    times: np.ndarray,
    block: int,
    arrival: np.ndarray | Reader | None = None,
) -> Iterator[tuple[int, int, dict[str, tuple[np.ndarray, np.ndarray]]]]:
    """(k0, k1, {arch: (mean (1, w, n), cov (1, w, n, n))}) of each block of `block` instants
    of a one-run log on the instants `times` (K+1,) s, in order (`estimate_steps`' numbers).
    Late sensors: each reading arrives at `arrival` (1, K+1, S) s, or `arrival(k0, k1)`
    (1, k1 - k0, S) s read a block at a time, default the sensors' fixed latencies (`_late`)."""
    K1 = len(times)
    edges = [(k0, min(k0 + block, K1)) for k0 in range(0, K1, block)]
    z0 = read(*edges[0])
    held = {"k0": 0, "z": z0}  # the block the filters read
    gens: dict[str, Iterator] = {}
    smoothers: dict[str, _Smoother] = {}
    for a in archs:
        if require_filter(system, a).locals == "smoother":
            smoothers[a] = _Smoother(system, a, times, edges, read)
        elif is_late(system):
            gens[a] = _named(_late(system, a, z0, times, read, block, arrival), a)
        else:
            m = machine_of(_Steps(system, z0, times, 0), a)
            gens[a] = _named(_fed(m, K1, held), a)
    for b, (k0, k1) in enumerate(edges):
        held.update(k0=k0, z=read(k0, k1))
        out = {}
        for a in archs:
            if a in smoothers:
                out[a] = smoothers[a].block(b)
                continue
            got = _Out(1, k1 - k0, system.n)
            for j in range(k1 - k0):
                got.put(j, *next(gens[a]))
            tr = got.track()
            out[a] = (tr.mean, tr.cov)
        yield k0, k1, out


def _late(system, arch, z0, times, read: Reader, block: int, arrival) -> Iterator:
    """`arch`'s filters under the late policy (`late.late_steps`): what crosses a block edge
    -- the states a reprocess rewinds to, the estimates Al1 retrodicts from, the readings of
    the last W instants with their arrival instants, neglect's newest measurement times -- is
    held by the policy and its `late_feed.Feed`, which reads the log a block at a time."""
    st = _Steps(system, z0, times, 0)
    m = machine_of(st, arch)
    filters = late_filters(m, arch)
    arrive = fixed_arrivals(st.system, st.times, arrival)
    return late_steps(m, filters, arrive, read, block)


def _fed(m: Machine, K1: int, held: dict, first: int = 0, state=None):
    """The machine over the instants first..K1-1 from `state` (None: its start), instant k's
    readings from the block `held` holds ({"k0", "z" (1, w, m)}) when k is asked for."""
    s = m.start() if state is None else state
    for k in range(first, K1):
        s = m.step(k, s, held["z"][:, k - held["k0"]])
        yield m.out(s)


class _Smoother:
    """FBS of one log in blocks (the module's recomputation): `block(b)` its estimates of
    block b, (mean (1, w, n), cov (1, w, n, n))."""

    def __init__(
        self,
        system: System,
        arch: str,
        times: np.ndarray,
        edges: list[tuple[int, int]],
        read: Reader,
    ) -> None:
        self.arch, self.edges, self.read = arch, edges, read
        self.st = _Steps(system, read(*edges[0]), times, 0)
        self.K1 = len(times)
        self.held: dict = {}
        # the forward filter's estimate before each block (None: the prior, at instant 0)
        self.starts: list = []
        state = None
        forward = _named(_fed(_filter_machine(self.st), self.K1, self.held), arch)
        for k0, k1 in edges:
            self.starts.append(state)
            self.held.update(k0=k0, z=read(k0, k1))
            for _ in range(k1 - k0):
                state = next(forward)
        # the smoothed estimate at the first instant after each block (None: the last block)
        self.after: list = [None] * len(edges)
        carried = None
        for b in range(len(edges) - 1, -1, -1):
            self.after[b] = carried
            mean, cov = self.block(b)
            # copies: views of the block's first instant would keep its whole arrays (mean
            # and covariances of every instant of it) alive for the rest of the log
            carried = (mean[:, 0].copy(), cov[:, 0].copy())

    def block(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Block b's forward pass recomputed from its checkpoint, then smoothed backwards from
        the smoothed estimate after it (the prediction into that instant recomputed too)."""
        k0, k1 = self.edges[b]
        st, w, after = self.st, k1 - k0, self.after[b]
        self.held.update(k0=k0, z=self.read(k0, k1))
        keep: list = []
        m = _filter_machine(st, keep)
        forward = _named(_fed(m, self.K1, self.held, k0, self.starts[b]), self.arch)
        out = _Out(st.z.shape[0], w + (after is not None), st.system.n)
        for j in range(w):
            x, P = next(forward)
            out.put(j, x, P)
        keep = keep[1:] if k0 else keep  # the prediction into k0 is the block before's
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            if after is not None:
                xp, Pp, _, C = st.predict(k1, x, P)
                keep.append((xp, Pp, C))
                out.put(w, *after)
            tr = out.track()
            rts(tr.mean, tr.cov, keep)
        return tr.mean[:, :w], tr.cov[:, :w]
