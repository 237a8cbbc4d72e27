"""Series: one recorded stream in time order, and the checks every source shares.

A source (MCAP topic or CSV file) adds its messages in file order to a :class:`Collector`;
``finish`` drops messages whose values are NaN/inf (counted), sorts by measurement time
(stable, counted), and refuses two messages at one instant.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusionlog.errors import ValidationError

__all__ = ["Collector", "Series", "fail"]

INT64_MAX = 2**63 - 1
# a `time` field more than this off the offset (time - log time) that the stream's other
# messages keep (their median) is an unset or foreign stamp (a header stamp of 0)
FAR_NS = 60 * 10**9


@dataclass(frozen=True)
class Series:
    """One recorded stream: N messages in time order."""

    times_ns: np.ndarray  # (N,) int64, the measurement times (ns), sorted ascending (stable)
    values: np.ndarray  # (N, d) float64
    cov: np.ndarray | None  # (N, d, d) the per-message covariance blocks, or None when not asked
    notes: tuple[str, ...]  # counted, reported skips/fixes
    #: (N,) int64 the log/record time (ns) of each message, in the order of `times_ns`, where
    #: the time is a field of the message (a header stamp): when the message was logged, i.e.
    #: received (``arrival = "log_time"``, DESIGN.md "Late measurements"); None otherwise
    record_ns: np.ndarray | None = None


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
        # typed arrays, not lists of Python numbers: a 10^6-row log in 24 MB, not ~200 MB
        self._times = array("q")
        self._values = array("d")
        self._covs: list[np.ndarray] = []
        self._origin = array("q")
        self._record = array("q")  # the log/record times, when the time is a field
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

    def has_duplicates(self) -> bool:
        """Whether two items kept have the same time."""
        t = np.frombuffer(self._times, dtype=np.int64)
        if (t[1:] > t[:-1]).all():  # the usual case: increasing, no sort needed
            return False
        s = np.sort(t)
        return bool((s[1:] == s[:-1]).any())

    def _far(self, t: np.ndarray, record: np.ndarray | None) -> str | None:
        """A note on the items whose time is far from their log time, by the others' offset."""
        if record is None:
            return None
        off = t - record
        typical = int(np.median(off))
        far = np.flatnonzero(np.abs(off - typical) > FAR_NS)
        if not far.size:
            return None
        i = int(far[0])
        return (
            f"{_plural(far.size, self.unit)} whose time is more than {FAR_NS // 10**9} s off "
            f"the others' (time - log time {typical / 1e9:.6g} s for most), e.g. "
            f"{self.label(self._origin[i])}: time {int(t[i])} ns at log time "
            f"{int(record[i])} ns: an unset or foreign stamp? (kept)"
        )

    def finish(self) -> Series:
        notes: list[str] = []
        u = self.unit
        if self.bad_times:
            notes.append(f"{_plural(self.bad_times, u)} with a NaN or infinite time skipped")
        if self.bad_values:
            notes.append(f"{_plural(self.bad_values, u)} with {self.missing} values skipped")
        if not self._times:
            raise fail(
                self.source,
                self.what,
                f"no {u} with finite values and time (of {self.seen} read)"
                if self.seen
                else f"no {u}s",
            )
        # each buffer released once copied: a long log's rows are held once, not twice
        t = np.frombuffer(self._times, dtype=np.int64).copy()
        self._times = array("q")
        record = (
            np.frombuffer(self._record, dtype=np.int64).copy()
            if len(self._record) == len(t)
            else None
        )
        far = self._far(t, record)
        recorded, self._record = bool(self._record), array("q")
        if far:
            notes.append(far)
        values = np.frombuffer(self._values, dtype=np.float64).reshape(len(t), self.d).copy()
        self._values = array("d")
        cov = (
            np.array(self._covs, dtype=np.float64).reshape(len(t), self.d, self.d)
            if (self.with_cov)
            else None
        )
        # increasing (the usual case): no running maximum nor sort order of the log's length
        late = (
            0
            if (t[1:] >= t[:-1]).all()
            else int(np.count_nonzero(t[1:] < np.maximum.accumulate(t)[:-1]))
        )
        order = np.argsort(t, kind="stable") if late or not self._bulk else None
        if late:
            notes.append(f"{_plural(late, u)} out of time order (sorted)")
            t, values = t[order], values[order]
            cov = cov[order] if cov is not None else None
            record = record[order] if record is not None else None
        dup = np.flatnonzero(t[1:] == t[:-1])
        if dup.size:
            if self._bulk:  # a programming error: add_rows' caller checks has_duplicates
                raise RuntimeError("duplicate times among rows added without their origins")
            i = int(dup[0])
            a, b = sorted((self._origin[order[i]], self._origin[order[i + 1]]))
            more = np.unique(t[dup]).size - 1
            unset = recorded and not t[i]  # a header stamp of 0 from a field
            raise fail(
                self.source,
                self.what,
                f"duplicate instant {int(t[i])} ns: {self.label(a)} and {self.label(b)} have the "
                f"same time" + (f" ({_plural(more, 'more duplicated instant')})" if more else "")
                + (": an unset stamp? (without `time`, the log time is used)" if unset else ""),
            )  # fmt: skip
        if self.bad_covs:
            notes.append(
                f"{_plural(self.bad_covs, u)} with NaN or infinite covariance entries "
                "(returned as read)"
            )
        return Series(times_ns=t, values=values, cov=cov, notes=tuple(notes), record_ns=record)
