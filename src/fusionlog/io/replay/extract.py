"""What one decoded message gives a stream: its values, time and covariance block.

Shared by the MCAP and bag sources (:mod:`.mcap_source`, :mod:`.bag_source`): both decode
messages with the ecosystem's libraries and read them with the same field paths.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from math import isqrt
from pathlib import Path
from typing import Any

import numpy as np

from .fields import (
    TIME_UNITS,
    FieldPath,
    PathError,
    describe,
    is_array,
    parse_path,
    to_number,
    to_time_ns,
)
from .series import Collector, fail

__all__ = ["Extractor", "StreamFields"]


@dataclass(frozen=True)
class StreamFields:
    """Where a stream's readings are in each message or row: ``values`` (field paths or
    columns), ``time`` (a field or column; None: the record's own time) in ``time_unit``, and
    the ``covariance`` field with its rows/columns ``covariance_index`` that belong to
    ``values``. The same for every source format (:func:`fusionlog.io.replay.read_series`)."""

    values: Sequence[str]
    time: str | None = None
    time_unit: str = "s"
    covariance: str | None = None
    covariance_index: Sequence[int] | None = None

    def check(self, source: Path, what: str) -> None:
        """One-line errors for keys of the wrong type or shape, before any file is read."""
        values, time, covariance = self.values, self.time, self.covariance
        if isinstance(values, str) or not values:
            raise fail(source, what, "values must be a non-empty list of field paths or columns")
        for v in values:
            if not isinstance(v, str) or not v.strip():
                raise fail(source, what, f"values: {v!r} is not a field path or column name")
        if time is not None and (not isinstance(time, str) or not time.strip()):
            raise fail(source, what, f"time: {time!r} is not a field path or column name")
        if self.time_unit not in TIME_UNITS:
            units = ", ".join(TIME_UNITS)
            raise fail(source, what, f"time_unit {self.time_unit!r} is not one of {units}")
        if covariance is not None and (not isinstance(covariance, str) or not covariance.strip()):
            raise fail(source, what, f"covariance: {covariance!r} is not a field path")
        if self.covariance_index is None:
            return
        if covariance is None:
            raise fail(source, what, "covariance_index is given without covariance")
        idx = list(self.covariance_index)
        if not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in idx):
            raise fail(source, what, f"covariance_index {idx} must be non-negative integers")
        if len(idx) != len(values):
            raise fail(
                source,
                what,
                f"covariance_index has {len(idx)} entries but values has {len(values)}: one "
                "row/column of the covariance per value",
            )
        if len(set(idx)) != len(idx):
            raise fail(source, what, f"covariance_index {idx} repeats a row/column")


def _path(source: Path, what: str, text: str, key: str) -> FieldPath:
    try:
        return parse_path(text)
    except PathError as e:
        raise fail(source, what, f"{key}: {e}") from None


class _Covariance:
    """Extracts ``M[np.ix_(idx, idx)]`` from a flat row-major square matrix field."""

    def __init__(self, path: FieldPath, index: Sequence[int] | None, d: int) -> None:
        self.path, self.index, self.d = path, index, d
        self.n: int | None = None
        self.ix: Any = None

    def block(self, value: Any) -> np.ndarray:
        p = self.path.text
        if not is_array(value) or isinstance(value, bytes | bytearray | memoryview):
            raise PathError(f"covariance {p} is {describe(value)}, not an array of numbers")
        n = len(value)
        if self.n is None:
            k = isqrt(n)
            if n == 0 or k * k != n:
                raise PathError(f"covariance {p} has {n} numbers, not a square matrix")
            idx = list(range(k)) if self.index is None else list(self.index)
            if self.index is None and k != self.d:
                raise PathError(
                    f"covariance {p} is {k}x{k} but values has {self.d} components: give "
                    "covariance_index (its rows/columns that belong to values)"
                )
            bad = [i for i in idx if i >= k]
            if bad:
                raise PathError(
                    f"covariance_index {bad[0]} is out of range for the {k}x{k} matrix {p}"
                )
            self.n, self.ix = n, np.ix_(idx, idx)
        elif n != self.n:
            raise PathError(f"covariance {p} has {n} numbers where the first message had {self.n}")
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            flat = value.astype(np.float64)
        elif all(type(x) is float for x in value):
            flat = np.array(value, dtype=np.float64)
        else:
            flat = np.array([to_number(x, f"{p}[{j}]") for j, x in enumerate(value)])
        k = isqrt(n)
        return flat.reshape(k, k)[self.ix]


class Extractor:
    """The parsed field paths of a stream; ``read`` applies them to one decoded message."""

    def __init__(self, source: Path, what: str, fields: StreamFields) -> None:
        f = fields
        self.source, self.what = source, what
        self.values = [_path(source, what, v, "values") for v in f.values]
        self.time = _path(source, what, f.time, "time") if f.time is not None else None
        self.time_unit = f.time_unit
        self.cov = (
            _Covariance(
                _path(source, what, f.covariance, "covariance"), f.covariance_index, len(f.values)
            )
            if f.covariance is not None
            else None
        )

    def collector(self) -> Collector:
        """A :class:`Collector` for this stream's messages, in file order."""
        d = len(self.values)
        return Collector(
            self.source, self.what, d, self.cov is not None, "message", lambda k: f"message {k}"
        )

    def add(
        self, col: Collector, k: int, decoded: Any, default_time: int, topic: str, kind: str
    ) -> None:
        """Message k (1-based) of `topic` (of type `kind`) into `col`; a path that does not fit
        the message is a one-line error naming the topic, its type and the message."""
        try:
            t, vals, block = self.read(decoded, default_time)
        except PathError as e:
            where = f"topic {topic} ({kind})" + (f", message {k}" if k > 1 else "")
            raise fail(self.source, self.what, f"{where}: {e}") from None
        col.add(k, t, vals, block, record_ns=default_time if self.time is not None else None)

    def read(self, decoded: Any, default_time: int) -> tuple[int | None, list[float], Any]:
        """(time ns or None for NaN, values, covariance block or None); PathError when a path
        does not fit the message. ``default_time``: the log/record time of the message."""
        vals = [to_number(p.resolve(decoded), p.text) for p in self.values]
        if self.time is None:
            t: int | None = default_time
        else:
            t = to_time_ns(self.time.resolve(decoded), self.time.text, self.time_unit)
        cov = self.cov
        block = cov.block(cov.path.resolve(decoded)) if cov is not None else None
        return t, vals, block
