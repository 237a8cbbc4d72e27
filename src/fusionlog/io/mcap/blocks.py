"""Assembling blocks of runs from decoded tables, for :meth:`McapFile.iter_run_blocks`.

A file holds, for each block of runs (contiguous from run 0), for each step k = 0..K, for each
topic, one message (DESIGN.md, "MCAP files"). The reader asks for output blocks of its own size;
:class:`Assembly` copies each table's rows into the output blocks their runs fall in, with a few
numpy operations per topic and table (no Python per message), and checks the file's order on
the way (every step once per topic and block, runs and payload sizes consistent).

An estimate's covariance of n*n values is shared by the message's runs; an output block keeps
one (S, n, n) array as long as every file block it meets shares the same covariances, and
switches to per-run (runs, S, n, n) otherwise.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.errors import FusionlogError

from .columns import Table, gather
from .schema import ESTIMATE, VALUES

__all__ = ["Assembly", "Cursor", "Window"]

_F8 = np.dtype("<f8")
#: Messages with at least this many values are copied one by one (`Assembly.add_rows`).
_LARGE = 1024


@dataclass
class _Est:
    """Assembly buffers of one estimate topic in one output block."""

    mean: np.ndarray
    shared: np.ndarray | None = None  # (S, n, n) while every file block had one shared cov
    per_run: np.ndarray | None = None  # (runs, S, n, n) once covariances differ between runs

    def to_per_run(self, runs: int) -> None:
        """Switch to per-run covariances; rows filled so far had the shared one."""
        m = self.mean.shape
        self.per_run = np.empty((runs, m[1], m[2], m[2]))
        if self.shared is not None:
            self.per_run[:] = self.shared


def _same_bits(a: np.ndarray, b: np.ndarray, piece: int = 1 << 16) -> bool:
    """``a.tobytes() == b.tobytes()`` (bit for bit: NaNs alike, -0.0 unlike 0.0), compared
    piece by piece rather than through two copies of the whole arrays."""
    if a.shape != b.shape:
        return False
    fa, fb = a.reshape(-1), b.reshape(-1)
    return all(
        fa[i : i + piece].tobytes() == fb[i : i + piece].tobytes() for i in range(0, fa.size, piece)
    )


@dataclass
class _OutBlock:
    lo: int
    hi: int
    arrays: dict[int, Any] = field(default_factory=dict)  # topic index -> ndarray | _Est


@dataclass(frozen=True)
class Window:
    """Runs [a, b) of the file block of runs [o, o + r); check: validate its messages (first
    reading) or trust them (a window read again)."""

    o: int
    r: int
    a: int
    b: int
    check: bool


#: Where reading stands: a (chunk ordinal, table) and a row of it; no table at the end.
Cursor = tuple[tuple[int, "Table"] | None, int]


class Assembly:
    """Copies decoded tables into output blocks of runs.

    Holds at most two output blocks (``pending``) and, for the file block being read, which
    steps each topic had and the shared covariances met so far (reset by ``end_block``).
    """

    def __init__(
        self,
        path: Path,
        names: list[str],
        dims: list[int],
        kinds: list[str],
        topic_index: np.ndarray,
        masks: list[np.ndarray],
        total: int,
        block_runs: int,
    ) -> None:
        self.path, self.names, self.dims, self.kinds = path, names, dims, kinds
        self.topic_index = topic_index  # channel id -> index into names
        # masks[ti]: the instants at which topic ti has a message (a sensor at its own rate
        # has some); the others are NaN in its output arrays.
        steps = len(masks[0]) if masks else 0
        self.masks = masks
        self.S, self.total, self.block_runs = steps, total, block_runs
        self.pending: list[_OutBlock] = []
        self.next_lo = 0
        self.seen = [np.zeros(steps, bool) for _ in names]
        self.shared = [
            np.zeros((steps, d, d)) if k == ESTIMATE else None
            for k, d in zip(kinds, dims, strict=True)
        ]
        self.has_shared = [np.zeros(steps, bool) for _ in names]
        self.any_per_run = [False for _ in names]

    def bad(self, msg: str) -> FusionlogError:
        return FusionlogError(f"{self.path}: {msg} (fusionlog block order violated)")

    def add_blocks(self, upto: int) -> int:
        """Open output blocks (at most two) towards run ``upto``; return the window end."""
        pending = self.pending
        while (
            len(pending) < 2
            and (not pending or pending[-1].hi < upto)
            and self.next_lo < self.total
        ):
            lo, hi = self.next_lo, min(self.next_lo + self.block_runs, self.total)
            blk = _OutBlock(lo, hi)
            for ti, d in enumerate(self.dims):
                shape = (hi - lo, self.S, d)
                if self.kinds[ti] != VALUES:
                    blk.arrays[ti] = _Est(np.empty(shape))
                elif self.masks[ti].all():
                    blk.arrays[ti] = np.empty(shape)
                else:  # no message at some instants: NaN there, the mark of a missing value
                    blk.arrays[ti] = np.full(shape, np.nan)
            pending.append(blk)
            self.next_lo = hi
        return min(upto, pending[-1].hi)

    def overlaps(self, w: Window) -> Iterator[tuple[_OutBlock, slice, slice]]:
        """Output blocks meeting the window's runs: (block, its rows, rows of the window)."""
        for blk in self.pending:
            x, y = max(w.a, blk.lo), min(w.b, blk.hi)
            if x < y:
                yield blk, slice(x - blk.lo, y - blk.lo), slice(x - w.a, y - w.a)

    def read_block(self, tables: Iterator[tuple[int, Table]], cur: Cursor, w: Window) -> Cursor:
        """Copy the window of the file block that starts at ``cur`` into the output blocks;
        return where the next file block starts."""
        item, i = cur
        while item is not None:
            tab = item[1]
            other = np.flatnonzero(tab.off[i:] != w.o)
            j = i + int(other[0]) if len(other) else len(tab)
            self.add_rows(tab, i, j, w)
            if j < len(tab):
                i = j
                break
            item, i = next(tables, None), 0
        self.end_block(w)
        return item, i

    def check_rows(self, tab: Table, sel: np.ndarray, ti: int, w: Window) -> None:
        """The messages ``sel`` of topic ``ti`` fit the file block at run ``w.o``."""
        name, d, o, r = self.names[ti], self.dims[ti], w.o, w.r
        steps = tab.step[sel]
        wrong = np.flatnonzero(tab.runs[sel] != r)
        if len(wrong):
            i = sel[wrong[0]]
            raise self.bad(
                f"{name}: messages of the block at run {o} disagree on runs (step "
                f"{tab.step[i]} has runs={tab.runs[i]}, the block's first message {r})"
            )
        if steps.max() >= self.S:
            raise self.bad(f"{name}: step {steps.max()} beyond the file's {self.S} steps")
        # twice: in an earlier table of this block, or twice in this one
        twice = steps[self.seen[ti][steps]]
        if not len(twice):
            ordered = np.sort(steps)
            twice = ordered[1:][ordered[1:] == ordered[:-1]]
        if len(twice):
            raise self.bad(f"{name}: step {twice[0]} appears twice for runs from {o}")
        wrong = np.flatnonzero((tab.dim[sel] != d) | (tab.n1[sel] != r * d * 8))
        if len(wrong):
            i = sel[wrong[0]]
            raise FusionlogError(
                f"{self.path}: {name}: step {tab.step[i]} runs from {o}: payload of "
                f"{tab.n1[i] // 8} doubles does not match runs={r}, dim={tab.dim[i]} "
                f"(topic dim {d})"
            )
        if self.kinds[ti] == VALUES:  # an optional per-message covariance of one run
            wrong = np.flatnonzero((tab.n2[sel] != 0) & (tab.n2[sel] != r * d * d * 8))
            if len(wrong):
                i = sel[wrong[0]]
                raise FusionlogError(
                    f"{self.path}: {name}: step {tab.step[i]} runs from {o}: covariance of "
                    f"{tab.n2[i] // 8} doubles is not runs*dim*dim"
                )
            # Refused here, not by `McapFile.message_covariances_of`, which reads only one-run
            # files: a file of more runs is read block by block anyway.
            carry = tab.n2[sel] != 0
            if self.total != 1 and carry.any():
                i = sel[int(np.argmax(carry))]
                raise FusionlogError(
                    f"{self.path}: {name}: step {tab.step[i]} runs from {o}: a message "
                    f"covariance in a file of {self.total} runs (per-message covariances are "
                    "for one-run logs)"
                )
        if self.kinds[ti] == ESTIMATE:
            n2 = tab.n2[sel]
            wrong = np.flatnonzero((n2 != d * d * 8) & (n2 != r * d * d * 8))
            if len(wrong):
                i = sel[wrong[0]]
                raise FusionlogError(
                    f"{self.path}: {name}: step {tab.step[i]} runs from {o}: covariance of "
                    f"{tab.n2[i] // 8} doubles is neither n*n nor runs*n*n"
                )

    def add_rows(self, tab: Table, i: int, j: int, w: Window) -> None:
        """Copy the window's runs of rows [i, j) of ``tab`` into the output blocks."""
        of_topic = self.topic_index[tab.cid[i:j]]
        rows, skip = w.b - w.a, w.a - w.o  # a window's rows of a message: from row a - o on
        for ti, d in enumerate(self.dims):
            sel = i + np.flatnonzero(of_topic == ti)
            if not len(sel):
                continue
            if w.check:
                self.check_rows(tab, sel, ti, w)
            steps = tab.step[sel]
            self.seen[ti][steps] = True
            estimate = self.kinds[ti] == ESTIMATE
            outs = [
                (blk.arrays[ti].mean if estimate else blk.arrays[ti], dst, src)
                for blk, dst, src in self.overlaps(w)
            ]
            starts = tab.p1[sel] + skip * d * 8
            if rows * d >= _LARGE:
                # Few large messages (a block of many runs): each payload straight from the
                # chunk's bytes into its step of the output, a basic slice; numpy's
                # fancy-index assignment of them all moves d values at a time through its
                # map iterator, 1.5x slower, after a gathered copy.
                for k, start in zip(steps.tolist(), starts.tolist(), strict=True):
                    v = np.frombuffer(tab.raw, _F8, rows * d, start).reshape(rows, d)
                    for out, dst, src in outs:
                        out[dst, k] = v[src]
            else:
                vals = gather(tab.raw, starts, rows * d).reshape(len(sel), rows, d)
                for out, dst, src in outs:
                    out[dst, steps] = vals[:, src].swapaxes(0, 1)
            if not estimate:
                continue
            # A covariance of n*n values is shared by the message's runs (for a one-run
            # message both readings agree); shared ones are placed when the block ends.
            sh = tab.n2[sel] == d * d * 8
            if sh.any():
                k = steps[sh]
                self.shared[ti][k] = gather(tab.raw, tab.p2[sel[sh]], d * d).reshape(-1, d, d)  # type: ignore[index]
                self.has_shared[ti][k] = True
            if not sh.all():
                self.any_per_run[ti] = True
                pr = sel[~sh]
                covs = gather(tab.raw, tab.p2[pr] + skip * d * d * 8, rows * d * d)
                covs = covs.reshape(len(pr), rows, d, d)
                for blk, dst, src in self.overlaps(w):
                    est: _Est = blk.arrays[ti]
                    if est.per_run is None:
                        est.to_per_run(blk.hi - blk.lo)
                    est.per_run[dst, steps[~sh]] = covs[:, src].swapaxes(0, 1)  # type: ignore[index]

    def end_block(self, w: Window) -> None:
        """Every step of every topic came; place the block's shared covariances; reset."""
        for ti, name in enumerate(self.names):
            seen = self.seen[ti]
            if w.check and not np.array_equal(seen, self.masks[ti]):
                raise self.bad(
                    f"{name}: {seen.sum()} of {self.masks[ti].sum()} steps for the block of runs "
                    f"at run {w.o}"
                )
            seen[:] = False
            cov, some = self.shared[ti], self.has_shared[ti]
            if cov is None:
                continue
            # The file's last window: nothing is read into the buffer again, so the output
            # block takes it as it is (a long log's covariances: 128 MB at 10^6 instants, n = 4)
            last = w.b >= self.total
            if last:
                self.shared[ti] = None
            for blk, dst, _ in self.overlaps(w):
                est: _Est = blk.arrays[ti]
                if self.any_per_run[ti]:  # est.per_run exists: add the steps that were shared
                    est.per_run[dst, some] = cov[some]  # type: ignore[index]
                    continue
                if est.per_run is None:
                    if est.shared is None:
                        # A copy per output block: writable, and not aliased between blocks
                        # that the caller may modify (the last window's buffer is nobody's).
                        est.shared = cov if last and len(self.pending) == 1 else cov.copy()
                        continue
                    if _same_bits(est.shared, cov):
                        continue
                    # Shared within each file block but different between them.
                    est.to_per_run(blk.hi - blk.lo)
                est.per_run[dst] = cov  # type: ignore[index]
            some[:] = False
            self.any_per_run[ti] = False

    def finished(self, upto: int) -> Iterator[tuple[int, int, dict[str, Any]]]:
        """Hand over the output blocks that end at or before run ``upto``."""
        while self.pending and self.pending[0].hi <= upto:
            blk = self.pending.pop(0)
            out: dict[str, Any] = {}
            for ti, t in enumerate(self.names):
                arr = blk.arrays[ti]
                if self.kinds[ti] == VALUES:
                    out[t] = arr
                else:
                    out[t] = (arr.mean, arr.shared if arr.per_run is None else arr.per_run)
            yield blk.lo, blk.hi - blk.lo, out
