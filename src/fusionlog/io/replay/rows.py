"""A stream's messages in an unnamed temporary file (issue 34: an hour-long log's readings are
not held while it is imported).

:class:`Rows` keeps one record per message — its time (``t``, int64 ns), values (``v``, d
doubles) and, where the stream has them, covariance block (``c``), log/record time (``r``)
and where it came from (``o``, for errors) — in an unnamed temporary file (deleted when
closed or collected), appended and read back a block of rows at a time: what a stream holds
in memory is a block, whatever its length. A `transform` of the values (geodetic fixes to
metres) applies as they are read. The file is a descriptor of an unlinked file, closed by a
finalizer when its `Rows` is collected (a reader that fails halfway leaves nothing open).
"""

from __future__ import annotations

import os
import tempfile
import weakref
from collections.abc import Callable, Iterator

import numpy as np

__all__ = ["BLOCK_ROWS", "Rows", "row_dtype"]

Transform = Callable[[np.ndarray], np.ndarray]

#: Rows read back at once (a few MB for a handful of values).
BLOCK_ROWS = 1 << 16


def row_dtype(d: int, cov: bool, record: bool, origin: bool) -> np.dtype:
    """The record of one message: t, v (d,) and c (d, d), r, o where asked."""
    fields = [("t", "<i8"), ("v", "<f8", (d,))]
    fields += [("c", "<f8", (d, d))] * cov + [("r", "<i8")] * record + [("o", "<i8")] * origin
    return np.dtype(fields)


class Rows:
    """Records of `dtype` appended in order to an unnamed temporary file and read back by
    blocks; `n` of them."""

    def __init__(self, dtype: np.dtype, transform: Transform | None = None) -> None:
        self.dtype = dtype
        fd, name = tempfile.mkstemp(prefix="fusionlog-rows-")
        os.unlink(name)  # unnamed: gone with its descriptor
        self.fd, self.n, self.transform = fd, 0, transform
        self._close = weakref.finalize(self, os.close, fd)

    def close(self) -> None:
        self._close()

    def has(self, name: str) -> bool:
        return name in (self.dtype.names or ())

    def append(self, block: np.ndarray) -> None:
        data = memoryview(np.ascontiguousarray(block, self.dtype)).cast("B")
        at = self.n * self.dtype.itemsize
        while data:
            done = os.pwrite(self.fd, data, at)
            data, at = data[done:], at + done
        self.n += len(block)

    def read(self, a: int, b: int) -> np.ndarray:
        """Records a..b-1 (the values transformed)."""
        a, b = max(0, a), min(self.n, b)
        out = np.empty(max(0, b - a), self.dtype)
        view, at = memoryview(out).cast("B"), a * self.dtype.itemsize
        while view:
            done = os.preadv(self.fd, [view], at)
            if not done:
                raise OSError(f"a temporary file of {self.n} records ended early")
            view, at = view[done:], at + done
        if self.transform is not None and len(out):
            out["v"] = self.transform(out["v"])
        return out

    def blocks(self, size: int = BLOCK_ROWS) -> Iterator[np.ndarray]:
        for a in range(0, self.n, size):
            yield self.read(a, a + size)

    def column(self, name: str) -> np.ndarray:
        """One field of every record (a whole stream's: for small logs and tests)."""
        shape = self.dtype[name].shape
        out = np.empty((self.n, *shape), self.dtype[name].base)
        for a in range(0, self.n, BLOCK_ROWS):
            out[a : a + BLOCK_ROWS] = self.read(a, a + BLOCK_ROWS)[name]
        return out

    def time_at(self, i: int) -> int:
        """The time of record i (negative i from the end)."""
        i = i % self.n
        return int(self.read(i, i + 1)["t"][0])

    def with_transform(self, fn: Transform) -> Rows:
        """The same file read with `fn` applied to the values."""
        out = Rows.__new__(Rows)
        out.dtype, out.fd, out.n, out.transform = self.dtype, self.fd, self.n, fn
        out._close, out._owner = self._close, self  # the file lives while either does
        return out
