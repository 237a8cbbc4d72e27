"""A replay's readings on their instants, a window of instants at a time (issue 34).

The instants are the sorted union of the sensors' measurement times (`fusionlog import`,
:mod:`.import_data`). Each sensor's messages are read back in time order from their unnamed
temporary file (`fusionlog.io.replay.rows.Rows`) a block at a time and merged: a window ends at
the earliest time up to which every sensor with messages left has been read, so every
message at or before it is in the window and none after. The truth is matched to a window's
instants on the samples around them (`TruthCursor`): those from the one before the window's
first instant to the one at or after its last, which hold each instant's neighbours, so
`core.associate.associate` gives what it gives on the whole truth. What is held is a block of
each stream and a window: nothing that grows with the log.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import numpy as np

from fusionlog.core.associate import associate
from fusionlog.io.replay.rows import BLOCK_ROWS, Rows

__all__ = ["Merged", "TruthCursor", "merged_windows"]


class Merged(NamedTuple):
    """A window: its instants (w,) ns and each sensor's records at them (in time order)."""

    instants: np.ndarray
    records: list[np.ndarray]


def _union(times: list[np.ndarray]) -> np.ndarray:
    """The sorted union (by a sort: numpy 2.4's np.unique hashes: 2 s for 2·10^6 times)."""
    every = np.concatenate(times)
    every.sort()
    return every[np.concatenate(([True], every[1:] != every[:-1]))]


def merged_windows(streams: list[Rows], size: int = BLOCK_ROWS) -> Iterator[Merged]:
    """The instants of the sorted `streams` and their records, window by window."""
    readers = [s.blocks(size) for s in streams]
    buf = [np.zeros(0, s.dtype) for s in streams]
    done = [False] * len(streams)
    while True:
        for j, r in enumerate(readers):
            if not done[j] and len(buf[j]) < size:
                nxt = next(r, None)
                if nxt is None:
                    done[j] = True
                else:
                    buf[j] = np.concatenate((buf[j], nxt)) if len(buf[j]) else nxt
        if not any(len(b) for b in buf):
            return
        more = [int(b["t"][-1]) for j, b in enumerate(buf) if not done[j]]
        cut = min(more) if more else None  # streams with messages left: read up to here
        take = [len(b) if cut is None else int(np.searchsorted(b["t"], cut, "right")) for b in buf]
        records = [b[:k] for b, k in zip(buf, take, strict=True)]
        buf = [b[k:] for b, k in zip(buf, take, strict=True)]
        yield Merged(_union([r["t"] for r in records]), records)


class TruthCursor:
    """The truth's samples (time-ordered records) matched to consecutive windows of instants."""

    def __init__(self, rows: Rows, match: str, max_diff_ns: int) -> None:
        self.rows, self.match, self.max_diff_ns = rows, match, max_diff_ns
        self._blocks = rows.blocks()
        self._buf = np.zeros(0, rows.dtype)
        self._done = False

    def at(self, instants: np.ndarray) -> np.ndarray:
        """(w, d) the truth's values at `instants` (after the last window's), NaN where none."""
        last = int(instants[-1])
        while not self._done and (not len(self._buf) or self._buf["t"][-1] < last):
            nxt = next(self._blocks, None)
            if nxt is None:
                self._done = True
            else:
                self._buf = np.concatenate((self._buf, nxt))
        t = self._buf["t"]
        a, b = np.searchsorted(t, [instants[0], last])
        near = self._buf[max(0, a - 1) : b + 1]  # each instant's samples before and at/after
        self._buf = self._buf[max(0, b - 1) :]  # the next window's first instant is after
        return associate(instants, near["t"], near["v"], self.match, self.max_diff_ns)
