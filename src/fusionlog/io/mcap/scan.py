"""What a scan of a file's first block of runs learns: each step's first time and, per topic,
the steps it has (`McapFile` where the ``fusionlog.layout`` record is absent, does not match,
or leaves the lists out past `.layout.LISTED` instants: issue 34).

Steps come in increasing order in every file fusionlog writes: their times are appended to a
packed array as the chunks come (8 bytes per instant, no per-chunk list of steps and times to
join and sort at the end); a file whose steps come otherwise is reduced as before, each
chunk's (steps, first times) kept and the first of each step taken at the end. Each topic's
steps are bits (`np.packbits` order), grown by doubling: a `.layout.StepMask` at the end.
"""

from __future__ import annotations

from array import array
from pathlib import Path

import numpy as np

from fusionlog.errors import FusionlogError

from .layout import StepMask

__all__ = ["ScanSteps"]


class ScanSteps:
    """Steps, their first times and each key's (a topic's) steps, fed a chunk at a time."""

    def __init__(self) -> None:
        self._times = array("d")  # steps 0..L-1, while the steps come in order
        self._parts: list[tuple[np.ndarray, np.ndarray]] | None = None  # once they do not
        self._bits: dict[int, np.ndarray] = {}

    def add(self, step: np.ndarray, time: np.ndarray, key: np.ndarray) -> None:
        """A chunk's messages of the first block, in file order: steps, times, keys."""
        if not len(step):
            return
        steps, at = np.unique(step, return_index=True)  # each step's first message here
        t = time[at]
        if self._parts is None:
            done = len(self._times)
            new = steps >= done  # the earlier steps' first times came in earlier chunks
            if np.array_equal(steps[new], np.arange(done, done + int(new.sum()))):
                self._times.frombytes(np.ascontiguousarray(t[new], "<f8").tobytes())
                self._mark(step, key)
                return
            self._parts = [(np.arange(done), np.frombuffer(self._times, np.float64).copy())]
            self._times = array("d")
        self._parts.append((steps, t))
        self._mark(step, key)

    def _mark(self, step: np.ndarray, key: np.ndarray) -> None:
        for k in np.unique(key).tolist():
            s = step[key == k].astype(np.int64)
            need = int(s.max()) // 8 + 1
            bits = self._bits.get(k)
            if bits is None or len(bits) < need:
                grown = np.zeros(max(need, 0 if bits is None else 2 * len(bits)), np.uint8)
                if bits is not None:
                    grown[: len(bits)] = bits
                bits = self._bits[k] = grown
            np.bitwise_or.at(bits, s >> 3, (128 >> (s & 7)).astype(np.uint8))

    def result(self, path: Path) -> tuple[np.ndarray, dict[int, StepMask]]:
        """(S,) times of steps 0..S-1 and each key's `StepMask`; a one-line error naming
        `path` where the steps are not 0..K."""
        if self._parts is None:
            times = np.frombuffer(self._times, np.float64) if self._times else np.zeros(0)
        else:
            steps, at = np.unique(np.concatenate([p[0] for p in self._parts]), return_index=True)
            if steps[-1] != len(steps) - 1:
                raise FusionlogError(
                    f"{path}: the steps of the first block of runs are not 0..K "
                    f"(found {len(steps)} distinct steps, largest {steps[-1]})"
                )
            times = np.concatenate([p[1] for p in self._parts])[at]
            self._parts = None
        size = (len(times) + 7) // 8
        masks = {}
        for k, bits in self._bits.items():
            b = bits[:size] if len(bits) >= size else np.pad(bits, (0, size - len(bits)))
            masks[k] = StepMask(b, len(times), int(np.bitwise_count(b).sum()))
        return times, masks
