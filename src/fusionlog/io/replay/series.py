"""Series: one recorded stream in time order, and the checks every source shares.

A source (MCAP topic or CSV file) adds its messages in file order to a :class:`Collector`;
``finish`` drops messages whose values are NaN/inf (counted), sorts by measurement time
(stable, counted), and refuses two messages at one instant.

The messages go to an unnamed temporary file a block at a time as they come (`.rows.Rows`,
issue 34): a stream holds a block of them in memory whatever its length, and the import reads
them back by blocks. Two things still take a whole stream while it is finished: a stream out of
time order is sorted in memory (its records), and a stream whose time is a field of its
messages holds its offsets to their log times (8 bytes a message) while their median is taken.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fusionlog.errors import ValidationError

from .rows import BLOCK_ROWS, Rows, row_dtype

__all__ = ["Collector", "Series", "fail"]

INT64_MAX = 2**63 - 1
# a `time` field more than this off the offset (time - log time) that the stream's other
# messages keep (their median) is an unset or foreign stamp (a header stamp of 0)
FAR_NS = 60 * 10**9


class Series:
    """One recorded stream: N messages in time order, their records in `rows` (read by
    blocks); each field as a whole array on access (small logs, tests):

    * ``times_ns`` (N,) int64, the measurement times (ns), sorted ascending (stable);
    * ``values`` (N, d) float64;
    * ``cov`` (N, d, d) the per-message covariance blocks, or None when not asked;
    * ``record_ns`` (N,) int64 the log/record time (ns) of each message where the time is a
      field of the message (a header stamp): when the message was logged, i.e. received
      (``arrival = "log_time"``, DESIGN.md "Late measurements"); None otherwise.

    ``notes``: counted, reported skips/fixes. Made from those arrays, or from records
    (`of_rows`)."""

    def __init__(self, times_ns, values, cov, notes, record_ns=None) -> None:
        values = np.asarray(values, dtype=np.float64)
        rows = Rows(row_dtype(values.shape[1], cov is not None, record_ns is not None, False))
        rec = np.zeros(len(values), rows.dtype)
        rec["t"], rec["v"] = times_ns, values
        if cov is not None:
            rec["c"] = cov
        if record_ns is not None:
            rec["r"] = record_ns
        rows.append(rec)
        self.rows, self.notes, self.recorded = rows, tuple(notes), record_ns is not None

    @classmethod
    def of_rows(cls, rows: Rows, notes: tuple[str, ...], recorded: bool = True) -> Series:
        out = cls.__new__(cls)
        out.rows, out.notes, out.recorded = rows, notes, recorded and rows.has("r")
        return out

    def __len__(self) -> int:
        return self.rows.n

    @property
    def times_ns(self) -> np.ndarray:
        return self.rows.column("t")

    @property
    def values(self) -> np.ndarray:
        return self.rows.column("v")

    @property
    def cov(self) -> np.ndarray | None:
        return self.rows.column("c") if self.rows.has("c") else None

    @property
    def record_ns(self) -> np.ndarray | None:
        return self.rows.column("r") if self.recorded else None


def fail(source: Path, what: str, problem: str) -> ValidationError:
    """The one-line error every check raises: ``<source>: <what>: <problem>``."""
    text = " ".join(f"{source}: {what}: {problem}".split())
    return ValidationError(text)


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


class Collector:
    """Accumulates (time, values, covariance) per message in file order.

    ``unit`` names the items in notes and errors ("message" or "row"); ``label(k)`` says
    where item k came from ("message 12", "line 14"); ``missing`` describes skipped values.
    """

    def __init__(
        self,
        source: Path,
        what: str,
        d: int,
        with_cov: bool,
        unit: str,
        label: Callable[[int], str],
        missing: str = "NaN or infinite",
    ) -> None:
        self.source, self.what, self.d, self.unit = source, what, d, unit
        self.missing = missing
        self.label = label
        self.with_cov = with_cov
        # typed arrays, not lists of Python numbers, flushed to `_rows` a block at a time
        self._times = array("q")
        self._values = array("d")
        self._covs: list[np.ndarray] = []
        self._origin = array("q")
        self._record = array("q")  # the log/record times, when the time is a field
        self._rows: Rows | None = None
        self._unrecorded = False  # some message without its log/record time
        self._bulk = False  # rows added by add_rows, without their origins
        self.bad_values = 0
        self.bad_times = 0
        self.bad_covs = 0
        self.seen = 0

    def add(
        self, origin: int, t_ns: int | None, values: list[float], cov=None, record_ns=None
    ) -> None:
        """Item `origin` at `t_ns` (None: NaN), with the log/record time `record_ns` of its
        message when `t_ns` comes from a field of it."""
        self.seen += 1
        if t_ns is None:
            self.bad_times += 1
            return
        if not 0 <= t_ns <= INT64_MAX:
            # an MCAP log_time is nanoseconds since 1970 in 63 bits (a signed int64 >= 0)
            why = "negative (before 1970)" if t_ns < 0 else "past 2^63 - 1 ns (the year 2262)"
            raise fail(
                self.source,
                self.what,
                f"{self.label(origin)}: time {t_ns} ns is {why}: a log's 64-bit nanosecond "
                "clock cannot hold it",
            )
        if not all(map(math.isfinite, values)):
            self.bad_values += 1
            return
        if self.with_cov:
            if not np.isfinite(cov).all():
                self.bad_covs += 1
            self._covs.append(cov)
        self._times.append(t_ns)
        self._values.extend(values)
        self._origin.append(origin)
        if record_ns is not None:
            self._record.append(record_ns)
        if len(self._times) >= BLOCK_ROWS:
            self._flush()

    def add_rows(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        """`add` for rows at once (a table read in blocks, `.text_fast`): times (m,) int64 all
        in [0, 2^63 - 1], values (m, d), kept in typed arrays (no Python object per row). The
        rows' origins are not kept: the caller refuses duplicate times (`has_duplicates`) and
        reads those again one by one, whose error names the lines."""
        self.seen += len(t_ns)
        good = np.isfinite(values).all(axis=1)
        self.bad_values += int(len(good) - np.count_nonzero(good))
        self._times.frombytes(np.ascontiguousarray(t_ns[good], dtype=np.int64).tobytes())
        self._values.frombytes(np.ascontiguousarray(values[good], dtype=np.float64).tobytes())
        self._bulk = True
        if len(self._times) >= BLOCK_ROWS:
            self._flush()

    def _flush(self) -> None:
        """The buffered items to `_rows` (made at the first flush, with the fields the
        stream has), the buffers emptied."""
        n = len(self._times)
        if not n:
            return
        if self._rows is None:
            record = len(self._record) == n
            self._rows = Rows(row_dtype(self.d, self.with_cov, record, not self._bulk))
        rows = self._rows
        rec = np.zeros(n, rows.dtype)
        rec["t"] = np.frombuffer(self._times, np.int64)
        rec["v"] = np.frombuffer(self._values, np.float64).reshape(n, self.d)
        if rows.has("c"):
            rec["c"] = np.array(self._covs, dtype=np.float64).reshape(n, self.d, self.d)
        if rows.has("r"):
            if len(self._record) == n:
                rec["r"] = np.frombuffer(self._record, np.int64)
            else:
                self._unrecorded = True
        if rows.has("o"):
            rec["o"] = np.frombuffer(self._origin, np.int64)
        rows.append(rec)
        self._times, self._values, self._covs = array("q"), array("d"), []
        self._origin, self._record = array("q"), array("q")

    def _increasing(self, strict: bool) -> bool:
        """Whether the items' times increase (strictly: no two equal), block by block."""
        last = None
        for b in self._rows.blocks() if self._rows is not None else ():
            t = b["t"]
            joined = t if last is None else np.concatenate(([last], t))
            d = joined[1:] - joined[:-1]
            if not ((d > 0) if strict else (d >= 0)).all():
                return False
            last = t[-1]
        return True

    def has_duplicates(self) -> bool:
        """Whether two items kept have the same time."""
        self._flush()
        if self._increasing(strict=True):  # the usual case: no sort needed
            return False
        s = np.sort(self._rows.column("t"))  # out of order: the times, sorted in memory
        return bool((s[1:] == s[:-1]).any())

    def _far(self, rows: Rows) -> str | None:
        """A note on the items whose time is far from their log time, by the others' offset
        (their median: the offsets of the whole stream held while it is taken)."""
        off = np.concatenate([b["t"] - b["r"] for b in rows.blocks()])
        typical = int(np.median(off))
        far = np.flatnonzero(np.abs(off - typical) > FAR_NS)
        if not far.size:
            return None
        i = int(far[0])
        row = rows.read(i, i + 1)[0]
        return (
            f"{_plural(far.size, self.unit)} whose time is more than {FAR_NS // 10**9} s off "
            f"the others' (time - log time {typical / 1e9:.6g} s for most), e.g. "
            f"{self.label(int(row['o']))}: time {int(row['t'])} ns at log time "
            f"{int(row['r'])} ns: an unset or foreign stamp? (kept)"
        )

    def _late(self, rows: Rows) -> int:
        """How many items come before the latest time of those above them in the file."""
        late, top = 0, None
        for b in rows.blocks():
            t = b["t"]
            run = np.maximum.accumulate(t)
            if top is not None:
                late += int(t[0] < top)
                run = np.maximum(run, top)
            late += int(np.count_nonzero(t[1:] < run[:-1]))
            top = run[-1]
        return late

    def _sorted(self, rows: Rows) -> Rows:
        """The records in time order (stable): sorted in memory, written to a new file."""
        whole = rows.read(0, rows.n)
        rows.close()
        out = Rows(rows.dtype)
        out.append(whole[np.argsort(whole["t"], kind="stable")])
        return out

    def _duplicate(self, rows: Rows) -> tuple[int, np.ndarray] | None:
        """The first index i with t[i] == t[i+1] of time-ordered records, and every such
        time; None where there is none."""
        first, times, last, at = None, [], None, 0
        for b in rows.blocks():
            t = b["t"]
            joined = t if last is None else np.concatenate(([last], t))
            dup = np.flatnonzero(joined[1:] == joined[:-1])
            if dup.size:
                first = first if first is not None else at + int(dup[0]) - (last is not None)
                times.append(joined[dup])
            last, at = t[-1], at + len(t)
        return None if first is None else (first, np.concatenate(times))

    def finish(self) -> Series:
        notes: list[str] = []
        u = self.unit
        if self.bad_times:
            notes.append(f"{_plural(self.bad_times, u)} with a NaN or infinite time skipped")
        if self.bad_values:
            notes.append(f"{_plural(self.bad_values, u)} with {self.missing} values skipped")
        self._flush()
        rows, self._rows = self._rows, None
        if rows is None:
            raise fail(
                self.source,
                self.what,
                f"no {u} with finite values and time (of {self.seen} read)"
                if self.seen
                else f"no {u}s",
            )
        recorded = rows.has("r") and not self._unrecorded
        far = self._far(rows) if recorded else None
        if far:
            notes.append(far)
        late = self._late(rows)
        if late:
            notes.append(f"{_plural(late, u)} out of time order (sorted)")
            rows = self._sorted(rows)
        dup = self._duplicate(rows)
        if dup is not None:
            if self._bulk:  # a programming error: add_rows' caller checks has_duplicates
                raise RuntimeError("duplicate times among rows added without their origins")
            i, times = dup
            pair = rows.read(i, i + 2)
            a, b = sorted(int(o) for o in pair["o"])
            more = np.unique(times).size - 1
            again = f" ({_plural(more, 'more duplicated instant')})" if more else ""
            unset = rows.has("r") and not int(pair["t"][0])  # a header stamp of 0 from a field
            raise fail(
                self.source,
                self.what,
                f"duplicate instant {int(pair['t'][0])} ns: {self.label(a)} and {self.label(b)} "
                f"have the same time{again}"
                + (": an unset stamp? (without `time`, the log time is used)" if unset else ""),
            )  # fmt: skip
        if self.bad_covs:
            notes.append(
                f"{_plural(self.bad_covs, u)} with NaN or infinite covariance entries "
                "(returned as read)"
            )
        return Series.of_rows(rows, tuple(notes), recorded)
