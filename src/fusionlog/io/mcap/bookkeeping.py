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

from .wire import encode_block_fields, encode_payload2_key

__all__ = ["FirstTimes", "StepSet", "TopicState"]


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

    def __len__(self) -> int:
        return self._count

    def sorted(self) -> list[int]:
        ranged = [k for a, b in zip(self._starts, self._ends, strict=True) for k in range(a, b)]
        return sorted([*ranged, *self._other]) if self._other else ranged


class FirstTimes:
    """step -> time, each step's first time kept (``dict.setdefault``): steps 0..L-1 in a packed
    array of doubles, steps that came before the ones below them in a dict until those come."""

    __slots__ = ("_dense", "_ahead")

    def __init__(self) -> None:
        self._dense = array("d")
        self._ahead: dict[int, float] = {}

    def setdefault(self, step: int, time: float) -> None:
        dense, ahead = self._dense, self._ahead
        if step < len(dense):
            return
        if step > len(dense):
            ahead.setdefault(step, time)
            return
        dense.append(ahead.pop(step, time))
        while ahead and len(dense) in ahead:  # steps that came early, now in sequence
            dense.append(ahead.pop(len(dense)))

    def extend(self, k0: int, times: array) -> None:
        """setdefault(k0 + i, times[i]) for each i (one append where k0 is the next step)."""
        if k0 == len(self._dense) and not self._ahead:
            self._dense.extend(times)
            return
        for i, t in enumerate(times):
            self.setdefault(k0 + i, t)

    def __len__(self) -> int:
        return len(self._dense) + len(self._ahead)

    def times(self) -> array | None:
        """The times of steps 0..S-1; None when the steps are not exactly those."""
        return None if self._ahead else self._dense


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
