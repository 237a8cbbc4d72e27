"""A stream's messages in an unnamed temporary file (issue 34: an hour-long log's readings are
not held while it is imported).

:class:`Rows` keeps one record per message — its time (``t``, int64 ns), values (``v``, d
doubles) and, where the stream has them, covariance block (``c``), log/record time (``r``)
and where it came from (``o``, for errors) — in an unnamed temporary file (deleted when
closed or collected), appended and read back a block of rows at a time: what a stream holds
in memory is a block, whatever its length. A `transform` of the values (geodetic fixes to
metres) applies as they are read.
"""

from __future__ import annotations

import tempfile
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
        self.file = tempfile.TemporaryFile(prefix="fusionlog-rows-")
        self.n = 0
        self.transform = transform

    def has(self, name: str) -> bool:
        return name in (self.dtype.names or ())

    def append(self, block: np.ndarray) -> None:
        self.file.seek(self.n * self.dtype.itemsize)
        np.ascontiguousarray(block, self.dtype).tofile(self.file)
        self.n += len(block)

    def read(self, a: int, b: int) -> np.ndarray:
        """Records a..b-1 (the values transformed)."""
        a, b = max(0, a), min(self.n, b)
        if b <= a:
            return np.zeros(0, self.dtype)
        self.file.seek(a * self.dtype.itemsize)
        out = np.fromfile(self.file, self.dtype, b - a)
        if self.transform is not None:
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
        self.file.seek(i * self.dtype.itemsize)
        return int(np.fromfile(self.file, self.dtype, 1)["t"][0])

    def with_transform(self, fn: Transform) -> Rows:
        """The same file read with `fn` applied to the values."""
        out = Rows.__new__(Rows)
        out.dtype, out.file, out.n, out.transform = self.dtype, self.file, self.n, fn
        return out
