"""Measurements from a CSV export (motion capture, loggers): one row per measurement.

Read with the standard library's :mod:`csv` (``skipinitialspace``, so ``a, b`` has the columns
``a`` and ``b``); the first non-blank row is the header, column names are matched exactly as
written there with surrounding spaces ignored (``#timestamp [ns]``, ``p_RS_R_x [m]``). Times are
parsed from the text with :class:`decimal.Decimal`, so integer nanoseconds stay exact and
``1700000000.123456789`` s is 1700000000123456789 ns. Blank lines are skipped. An empty,
``nan`` or ``inf`` value skips its row (counted); a row with the wrong number of fields or a
non-number is an error naming its line.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
from collections.abc import Sequence
from decimal import ROUND_HALF_EVEN, Context, Decimal, InvalidOperation
from pathlib import Path

from .fields import INT64_MAX, TIME_UNITS
from .series import Collector, Series, fail
from .source import MAX_TEXT_BYTES, bounded_lines, open_source

__all__ = ["read_csv"]

_CTX = Context(prec=80)


def _column(source: Path, what: str, header: list[str], name: str, key: str) -> int:
    want = name.strip()
    hits = [i for i, h in enumerate(header) if h == want]
    if len(hits) == 1:
        return hits[0]
    if len(hits) > 1:
        raise fail(source, what, f"{key}: column {want!r} appears {len(hits)} times in the header")
    close = difflib.get_close_matches(want, header, n=3, cutoff=0.5)
    if close:
        hint = "closest: " + ", ".join(repr(c) for c in close)
    else:
        cols = ", ".join(repr(h) for h in header[:12]) + (", ..." if len(header) > 12 else "")
        hint = f"columns: {cols}"
    raise fail(source, what, f"{key}: no column {want!r} in the header ({hint})")


def _time_ns(text: str, unit: str) -> int | None:
    """Nanoseconds, None for NaN/inf; ValueError for a non-number."""
    s = text.strip()
    if not s:
        raise ValueError("empty")
    try:
        d = Decimal(s)
    except InvalidOperation:
        raise ValueError("not a number") from None
    if not d.is_finite():
        return None
    try:
        ns = int(_CTX.multiply(d, TIME_UNITS[unit]).to_integral_value(rounding=ROUND_HALF_EVEN))
    except ArithmeticError:  # decimal.Overflow: beyond any clock
        raise ValueError("outside the range of 64-bit nanoseconds") from None
    if not -INT64_MAX - 1 <= ns <= INT64_MAX:
        raise ValueError("outside the range of 64-bit nanoseconds")
    return ns


def _number(text: str) -> float:
    s = text.strip()
    if not s:
        return math.nan  # an empty cell is a missing value: the row is skipped and counted
    return float(s)


def read_csv(
    source: Path, *, values: Sequence[str], time: str | None, time_unit: str, what: str
) -> Series:
    raw = open_source(source, what, MAX_TEXT_BYTES, "a text table")
    f = io.TextIOWrapper(raw, encoding="utf-8-sig", newline="")  # closed by the with below
    col = Collector(
        source, what, len(values), False, "row", lambda k: f"line {k}", "empty, NaN or infinite"
    )
    with f:
        lines = bounded_lines(f, MAX_TEXT_BYTES, source, what)
        reader = csv.reader(lines, skipinitialspace=True, strict=True)
        try:
            header = None
            for row in reader:
                if any(c.strip() for c in row):
                    header = [c.strip() for c in row]
                    break
            if header is None:
                raise fail(source, what, "empty CSV file (no header line)")
            tname = time if time is not None else "time"
            vcols = [_column(source, what, header, v, "values") for v in values]
            tcol = _column(
                source, what, header, tname, "time" if time is not None else "time (default)"
            )
            for row in reader:
                line = reader.line_num
                if not any(c.strip() for c in row):
                    continue
                if len(row) != len(header):
                    raise fail(
                        source,
                        what,
                        f"line {line}: {len(row)} fields where the header has {len(header)}",
                    )
                try:
                    t = _time_ns(row[tcol], time_unit)
                except ValueError as e:
                    cell = row[tcol].strip()[:40]
                    problem = "is empty" if not cell else f"{cell!r} is {e}"
                    raise fail(
                        source, what, f"line {line}: time column {header[tcol]!r} {problem}"
                    ) from None
                vals = []
                for c in vcols:
                    try:
                        vals.append(_number(row[c]))
                    except ValueError:
                        raise fail(
                            source,
                            what,
                            f"line {line}: column {header[c]!r}: {row[c].strip()[:40]!r} is not "
                            "a number",
                        ) from None
                col.add(line, t, vals)
        except csv.Error as e:
            raise fail(source, what, f"line {reader.line_num}: not valid CSV ({e})") from None
        except UnicodeDecodeError as e:
            raise fail(source, what, f"not UTF-8 text (byte {e.start}: {e.reason})") from None
    if col.seen == 0:
        raise fail(source, what, "no data rows after the header")
    return col.finish()
