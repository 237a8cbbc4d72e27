"""A long one-run log of a nonlinear model (EKF/UKF local filters) estimated in blocks of time
(issue 34), in memory that does not grow with its instants.

The filters (CKF, SKF, HKF and the track-to-track architectures, `.architectures`) compute
each instant from the instant before only: each keeps its state from block to block, its
readings fed one block at a time (`_Steps.feed`), so a block's estimates are the whole run's.

FBS, the extended / unscented RTS smoother, needs the instants after. Its forward filter is
*recomputed*, not written to disk: a first sweep keeps the filter's estimate (x, P) at the end
of each block (the checkpoints, one per block); a reverse sweep recomputes each block's forward
pass from the checkpoint before it and runs the backward pass (`rts`) from the smoothed
estimate at the first instant of the block after, keeping the block's own; handing the blocks
out in order recomputes each once more. Three forward and two backward passes of the CKF, the
readings read back block by block (`read`), one block in memory; the same operations on the
same numbers as the whole run's smoother.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np

from ..architectures.registry import definition, parse_arch
from ..model import System
from .architectures import _filter, _named, _Out, _Steps, require_filter, rts, steps_of

__all__ = ["estimate_blocks"]

#: The readings (1, w, m) of the instants k0..k1-1 (NaN: absent).
Reader = Callable[[int, int], np.ndarray]


def estimate_blocks(
    system: System,
    archs: Sequence[str],
    read: Reader,
    times: np.ndarray,
    block: int,
) -> Iterator[tuple[int, int, dict[str, tuple[np.ndarray, np.ndarray]]]]:
    """(k0, k1, {arch: (mean (1, w, n), cov (1, w, n, n))}) of each block of `block` instants
    of a one-run log on the instants `times` (K+1,) s, in order (`estimate_steps`' numbers)."""
    K1 = len(times)
    edges = [(k0, min(k0 + block, K1)) for k0 in range(0, K1, block)]
    names = [s.name for s in system.sensors]
    gens: dict[str, tuple[_Steps, Iterator]] = {}
    smoothers: dict[str, _Smoother] = {}
    for a in archs:
        require_filter(system, a)
        if definition(parse_arch(a, names)[0]).locals == "smoother":
            smoothers[a] = _Smoother(system, a, times, edges, read)
        else:
            st = _Steps(system, read(*edges[0]), times, 0, K1)
            gens[a] = (st, steps_of(st, a))
    for b, (k0, k1) in enumerate(edges):
        z = read(k0, k1)
        out = {}
        for a in archs:
            if a in smoothers:
                out[a] = smoothers[a].block(b)
                continue
            st, gen = gens[a]
            st.feed(k0, z)
            got = _Out(1, k1 - k0, system.n)
            for j in range(k1 - k0):
                got.put(j, *next(gen))
            tr = got.track()
            out[a] = (tr.mean, tr.cov)
        yield k0, k1, out


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
        self.st = _Steps(system, read(*edges[0]), times, 0, len(times))
        self.which = list(range(len(system.sensors)))
        # the forward filter's estimate before each block (None: the prior, at instant 0)
        self.starts: list = []
        state = None
        forward = _named(_filter(self.st, self.which), arch)
        for k0, k1 in edges:
            self.starts.append(state)
            self.st.feed(k0, read(k0, k1))
            for _ in range(k1 - k0):
                state = next(forward)
        # the smoothed estimate at the first instant after each block (None: the last block)
        self.after: list = [None] * len(edges)
        carried = None
        for b in range(len(edges) - 1, -1, -1):
            self.after[b] = carried
            mean, cov = self.block(b)
            carried = (mean[:, 0], cov[:, 0])

    def block(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Block b's forward pass recomputed from its checkpoint, then smoothed backwards from
        the smoothed estimate after it (the prediction into that instant recomputed too)."""
        k0, k1 = self.edges[b]
        st, w, after = self.st, k1 - k0, self.after[b]
        st.feed(k0, self.read(k0, k1))
        keep: list = []
        forward = _named(_filter(st, self.which, keep, k0, self.starts[b]), self.arch)
        out = _Out(st.M, w + (after is not None), st.system.n)
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
