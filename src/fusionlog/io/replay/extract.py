"""What one decoded message gives a stream: its values, time and covariance block.

Shared by the MCAP and bag sources (:mod:`.mcap_source`, :mod:`.bag_source`): both decode
messages with the ecosystem's libraries and read them with the same field paths.
"""

from __future__ import annotations

from collections.abc import Sequence
from math import isqrt
from pathlib import Path
from typing import Any

import numpy as np

from .fields import FieldPath, PathError, describe, is_array, parse_path, to_number, to_time_ns
from .series import fail

__all__ = ["Extractor"]


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

    def __init__(
        self,
        source: Path,
        what: str,
        values: Sequence[str],
        time: str | None,
        time_unit: str,
        covariance: str | None,
        covariance_index: Sequence[int] | None,
    ) -> None:
        self.values = [_path(source, what, v, "values") for v in values]
        self.time = _path(source, what, time, "time") if time is not None else None
        self.time_unit = time_unit
        self.cov = (
            _Covariance(
                _path(source, what, covariance, "covariance"), covariance_index, len(values)
            )
            if covariance is not None
            else None
        )

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
