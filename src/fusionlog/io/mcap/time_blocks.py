"""A one-run log read in blocks of time (issue 34: hour-long logs in bounded memory).

`McapFile.iter_run_blocks` hands over whole runs: for a log of one run of 10^6 instants that is
every reading at once. A one-run file is written instant by instant (DESIGN.md "MCAP files":
for each step, for each topic), so it can be read as consecutive windows of instants instead,
chunk by chunk, with only one window of arrays and one chunk of bytes held. The arrays have the
shapes of `iter_run_blocks` with the window's instants in place of K+1: a values topic
(1, w, dim) (NaN at instants without a message), an estimate topic (mean (1, w, n), cov (w, n, n)).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from fusionlog.errors import FusionlogError

from .columns import Table, gather
from .schema import ESTIMATE

__all__ = ["time_blocks"]


class _Window:
    """The arrays of the instants [k0, k1) of every topic, and which instants came."""

    def __init__(self, k0: int, k1: int, dims: list[int], kinds: list[str]) -> None:
        w = k1 - k0
        self.k0, self.k1 = k0, k1
        self.values: list[Any] = []
        for d, kind in zip(dims, kinds, strict=True):
            if kind == ESTIMATE:
                self.values.append((np.full((1, w, d), np.nan), np.full((w, d, d), np.nan)))
            else:
                self.values.append(np.full((1, w, d), np.nan))
        self.seen = [np.zeros(w, dtype=bool) for _ in dims]


def time_blocks(
    path: Any,
    tables: Iterator[tuple[int, Table]],
    names: Sequence[str],
    dims: Sequence[int],
    kinds: Sequence[str],
    topic_index: np.ndarray,
    masks: Sequence[Any],
    steps: int,
    instants: int,
) -> Iterator[tuple[int, int, dict[str, Any]]]:
    """(k0, k1, {topic: data}) for the windows [k0, k1) of `steps` instants of a one-run file
    of `instants` instants whose decoded chunks are `tables` (in file order), `masks[i]` the
    instants at which topic i has a message ((K+1,) bool, or a `StepMask` whose bits each window
    unpacks), None for every instant (nothing of the log's
    length held for it). A message out of time order, twice, or missing is a FusionlogError
    naming the file (the run reader's checks, per window)."""
    K1 = instants if names else 0
    dims, kinds = list(dims), list(kinds)
    win = _Window(0, min(steps, K1), dims, kinds)

    def flush(w: _Window) -> dict[str, Any]:
        for ti, name in enumerate(names):
            mask = masks[ti]
            want = True if mask is None else mask[w.k0 : w.k1]
            if not np.all(w.seen[ti] == want):
                k = w.k0 + int(np.flatnonzero(w.seen[ti] != want)[0])
                raise FusionlogError(f"{path}: {name}: step {k} missing or not scheduled")
        return dict(zip(names, w.values, strict=True))

    for _, tab in tables:
        order = np.argsort(tab.step, kind="stable")
        step, ti_of = tab.step[order], topic_index[tab.cid[order]]
        if len(step) and int(step[0]) < win.k0:
            raise FusionlogError(
                f"{path}: {names[ti_of[0]]}: step {int(step[0])} after step {win.k0} "
                "(a one-run log is read in time order)"
            )
        i = 0
        while i < len(step):
            j = int(np.searchsorted(step, win.k1, side="left"))
            if j > i:
                _place(path, tab, order[i:j], step[i:j], ti_of[i:j], win, names, dims, kinds)
            i = j
            if i < len(step):  # the window is complete: hand it over, start the next
                yield win.k0, win.k1, flush(win)
                if win.k1 >= K1:
                    raise FusionlogError(f"{path}: step {int(step[i])} beyond the file's {K1}")
                win = _Window(win.k1, min(win.k1 + steps, K1), dims, kinds)
    if K1:
        yield win.k0, win.k1, flush(win)
        if win.k1 < K1:
            raise FusionlogError(f"{path}: the messages end at step {win.k1} of {K1}")


def _place(path, tab: Table, rows, step, ti_of, win: _Window, names, dims, kinds) -> None:
    """Copy the rows (of one window) into its arrays."""
    for ti, d in enumerate(dims):
        sel = ti_of == ti
        if not sel.any():
            continue
        r, k = rows[sel], step[sel] - win.k0
        if (tab.runs[r] != 1).any() or (tab.off[r] != 0).any() or (tab.dim[r] != d).any():
            raise FusionlogError(f"{path}: {names[ti]}: not a one-run log of dim {d}")
        # (k is in order, the rows sorted by step: a step twice is two equal neighbours)
        if win.seen[ti][k].any() or (k[1:] == k[:-1]).any():
            raise FusionlogError(f"{path}: {names[ti]}: a step appears twice")
        win.seen[ti][k] = True
        vals = gather(tab.raw, tab.p1[r], d)
        if kinds[ti] == ESTIMATE:
            mean, cov = win.values[ti]
            mean[0, k] = vals
            cov[k] = gather(tab.raw, tab.p2[r], d * d).reshape(-1, d, d)
        else:
            win.values[ti][0, k] = vals
