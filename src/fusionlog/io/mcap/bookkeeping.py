"""The writer's per-message bookkeeping in machine words, not Python objects.

:class:`~.writer.McapWriter` remembers which steps each topic has in the block of runs being
written (to refuse a step written twice), the steps each topic has in the first block and the
time of each step there (the layout record). A long one-run log's first block is the whole
file: kept as a set of (channel, step) tuples, lists and a dict of floats, that took ~120
bytes per message (~0.5 GB for a 10^6-instant log of four topics, ~0.8 GB for its estimates
with seven architectures), so memory grew with the log far past its arrays. Steps come in
increasing order in every file fusionlog writes; stored as packed integers and doubles, with
a set only for steps that come out of order, the same facts take 4-8 bytes per message.
"""

from __future__ import annotations

from array import array
from bisect import bisect_right
from typing import Any

import numpy as np

from fusionlog.core.timing import regular_times

from .layout import LISTED, Layout, StepMask
from .wire import encode_block_fields, encode_payload2_key

__all__ = ["FirstTimes", "StepCounts", "StepSet", "TopicState", "first_block_layout"]


class StepSet:
    """A set of steps (uint32): those added in increasing order as packed ranges [start, end)
    (a topic that has every step, the usual case, is one range whatever the log's length:
    memory that does not grow with the instants, issue 34), the rest in a set."""

    __slots__ = ("_count", "_ends", "_other", "_starts")

    def __init__(self) -> None:
        self._starts = array("I")
        self._ends = array("Q")  # exclusive: a step of 2^32 - 1 ends at 2^32
        self._other: set[int] = set()
        self._count = 0

    def __contains__(self, step: int) -> bool:
        starts = self._starts
        if starts and step < self._ends[-1]:
            i = bisect_right(starts, step) - 1
            if i >= 0 and step < self._ends[i]:
                return True
        return step in self._other

    def add(self, step: int) -> None:
        """Add a step that is not in the set yet (the caller checks)."""
        self._count += 1
        ends = self._ends
        if ends and step == ends[-1]:
            ends[-1] = step + 1
        elif not ends or step > ends[-1]:
            self._starts.append(step)
            ends.append(step + 1)
        else:
            self._other.add(step)

    def add_range(self, a: int, b: int) -> int | None:
        """Add the steps a..b-1; return the first that was in the set already (then none is
        added), else None. One range appended where they follow the last step, as usual."""
        ends = self._ends
        if not ends or a >= ends[-1]:
            if not any(a <= k < b for k in self._other):
                if ends and a == ends[-1]:
                    ends[-1] = b
                else:
                    self._starts.append(a)
                    ends.append(b)
                self._count += b - a
                return None
        for k in range(a, b):
            if k in self:
                return k
        for k in range(a, b):
            self.add(k)
        return None

    def add_ranges(self, a: np.ndarray, b: np.ndarray) -> int | None:
        """`add_range` of each [a_i, b_i) (increasing, disjoint: a topic's runs of steps),
        appended at once where they follow the last step, as usual; the first step that was in
        the set already, else None."""
        ends = self._ends
        if not len(a) or self._other or (ends and a[0] < ends[-1]):
            for x, y in zip(a.tolist(), b.tolist(), strict=True):
                twice = self.add_range(x, y)
                if twice is not None:
                    return twice
            return None
        self._count += int((b - a).sum())
        i = 0
        if ends and a[0] == ends[-1]:  # the first run continues the last range
            ends[-1], i = int(b[0]), 1
        self._starts.frombytes(np.asarray(a[i:], dtype=np.uint32).tobytes())
        ends.frombytes(np.asarray(b[i:], dtype=np.uint64).tobytes())
        return None

    def __len__(self) -> int:
        return self._count

    def mask(self, instants: int) -> StepMask:
        """The set as a `StepMask` of the instants 0..instants-1 (its steps are below that),
        made from the ranges without a list of the steps."""
        edge = np.zeros(instants + 1, dtype=np.int8)
        edge[np.frombuffer(self._starts, np.uint32).astype(np.int64)] = 1
        edge[np.frombuffer(self._ends, np.uint64).astype(np.int64)] -= 1  # (ranges apart)
        inside = np.cumsum(edge[:-1], dtype=np.int8) > 0
        inside[list(self._other)] = True
        return StepMask(np.packbits(inside), instants, self._count)


class FirstTimes:
    """step -> time, each step's first time kept (``dict.setdefault``): steps 0..L-1 while
    t_k = k t_1 exactly (a simulation's k dt, which the layout records as ``dt``) as their
    count and t_1 alone, from the first other time on in a packed array of doubles; steps that
    came before the ones below them in a dict until those come. Past `LISTED` steps of other
    times only their count (the layout record does not list them: issue 34, `.layout`)."""

    __slots__ = ("_dense", "_ahead", "_n", "_dt", "_over")

    def __init__(self) -> None:
        self._dense: array | None = None  # None: steps 0.._n-1 at k * _dt, or _over
        self._n = 0
        self._dt = 0.0
        self._ahead: dict[int, float] = {}
        self._over = False  # past LISTED steps not at k * _dt: _n counts them, times not kept

    def _len(self) -> int:
        return self._n if self._dense is None else len(self._dense)

    def _cap(self) -> None:
        if self._dense is not None and len(self._dense) > LISTED:
            self._n, self._dense, self._over = len(self._dense), None, True

    def _append(self, t: float) -> None:
        if self._over:
            self._n += 1
            return
        if self._dense is None:
            n = self._n
            if n == 1:
                self._dt = t
            if (n == 0 and t == 0.0) or n == 1 or (n > 1 and t == n * self._dt):
                self._n += 1
                return
            self._dense = array("d", [k * self._dt for k in range(n)])
        self._dense.append(t)
        self._cap()

    def setdefault(self, step: int, time: float) -> None:
        ahead = self._ahead
        n = self._len()
        if step < n:
            return
        if step > n:
            ahead.setdefault(step, time)
            return
        self._append(ahead.pop(step, time))
        while ahead and self._len() in ahead:  # steps that came early, now in sequence
            self._append(ahead.pop(self._len()))

    def extend(self, k0: int, times: np.ndarray) -> None:
        """setdefault(k0 + i, times[i]) for each i (at once where k0 is the next step)."""
        if k0 != self._len() or self._ahead:
            for i, t in enumerate(times.tolist()):
                self.setdefault(k0 + i, t)
            return
        if self._over:
            self._n += len(times)
            return
        head = 2 if self._dense is None else 0  # t_0 and t_1 decide the regular steps
        for t in times[: max(0, head - self._n)].tolist():
            self._append(t)
        rest = times[max(0, head - k0) :]
        if self._dense is None:
            n = self._n
            if np.array_equal(np.arange(n, n + len(rest)) * self._dt, rest):
                self._n += len(rest)
                return
            for t in rest.tolist():  # the first other time makes the array
                self._append(t)
            return
        self._dense.frombytes(np.ascontiguousarray(rest, "<f8").tobytes())
        self._cap()

    def __len__(self) -> int:
        return self._len() + len(self._ahead)

    def steps(self) -> int | None:
        """S where the steps are exactly 0..S-1, else None."""
        return None if self._ahead else self._len()

    def times(self) -> np.ndarray | array | None:
        """The times of steps 0..S-1; None when the steps are not exactly those or their
        times were not kept (past `LISTED`)."""
        if self._ahead or self._over:
            return None
        return regular_times(self._n, self._dt) if self._dense is None else self._dense


class StepCounts:
    """A topic's steps in the first block of runs: a `StepSet` up to `LISTED` instants, past
    them only their count (the layout record does not list them: issue 34)."""

    __slots__ = ("set",)

    def __init__(self) -> None:
        self.set: StepSet | int = StepSet()

    def drop(self) -> None:
        """Keep the count alone."""
        if isinstance(self.set, StepSet):
            self.set = len(self.set)

    def add(self, step: int) -> None:
        if isinstance(self.set, StepSet):
            self.set.add(step)
        else:
            self.set += 1

    def add_ranges(self, a: np.ndarray, b: np.ndarray) -> None:
        if isinstance(self.set, StepSet):
            self.set.add_ranges(a, b)
        else:
            self.set += int((b - a).sum())

    def __len__(self) -> int:
        return self.set if isinstance(self.set, int) else len(self.set)


class TopicState:
    """Per-topic writer state: channel number and its log function (payload, log_time in ns;
    the SDK sets publish_time = log_time), kind, dim and the cached block fields."""

    __slots__ = ("cid", "log", "kind", "dim", "mid_key", "mid", "mid2", "seen")

    def __init__(self, cid: int, log: Any, kind: str, dim: int) -> None:
        self.cid, self.log, self.kind, self.dim = cid, log, kind, dim
        self.seen = StepSet()  # its steps in the current block of runs
        self.mid_key: tuple[int, int, int] | None = None
        self.mid = self.mid2 = b""

    def set_mid(self, run_offset: int, runs: int, cov_len: int) -> None:
        """Encode run_offset, runs, dim and the payload keys/lengths (fixed within a block)."""
        self.mid = encode_block_fields(run_offset, runs, self.dim, runs * self.dim * 8)
        self.mid2 = encode_payload2_key(cov_len)
        self.mid_key = (run_offset, runs, cov_len)


def first_block_layout(
    first_times: FirstTimes, first_steps: dict[str, StepCounts], dims: dict[str, int],
    runs: int, blocks: int,
) -> Layout | None:  # fmt: skip
    """A writer's layout record from its first block of runs; None where that block does not
    have steps 0..K (the reader then scans, and says what is wrong). Past `LISTED` instants,
    irregular times or a sparse topic are left out (`Layout.unlisted`, `.layout`)."""
    steps = first_times.steps()
    if steps is None:
        return None
    dense = first_times.times()
    sparse = [t for t, s in first_steps.items() if len(s) != steps and t in dims]
    if steps > LISTED and (dense is None or sparse):
        unlisted = ("times",) * (dense is None) + ("sparse",) * bool(sparse)
        return Layout(None, runs, blocks, dims, count=steps, unlisted=unlisted)
    masks = {t: first_steps[t].set.mask(steps) for t in sparse}  # type: ignore[union-attr]
    return Layout(np.asarray(dense, dtype=float), runs, blocks, dims, masks)
