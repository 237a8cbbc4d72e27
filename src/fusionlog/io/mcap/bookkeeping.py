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

__all__ = ["FirstTimes", "StepSet"]


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

    def __len__(self) -> int:
        return len(self._dense) + len(self._ahead)

    def times(self) -> array | None:
        """The times of steps 0..S-1; None when the steps are not exactly those."""
        return None if self._ahead else self._dense
