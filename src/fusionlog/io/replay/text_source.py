"""Measurements from a text table of any extension (CSV exports, TUM trajectories, loggers).

One row per measurement. The delimiter is given (``delimiter``: one character, or
``"whitespace"`` for runs of spaces and tabs) or found from the content: the first of comma,
tab, semicolon and whitespace that splits the first lines into the same number (> 1) of
fields. The first non-blank line is the header, its names matched exactly as written with
surrounding spaces ignored (``#timestamp [ns]``, ``p_RS_R_x [m]``), unless ``columns`` names the
columns; then every line starting with ``#`` is a comment. ``fmt = "tum"`` is the TUM trajectory
format: ``timestamp tx ty tz qx qy qz qw`` separated by whitespace, times in seconds, ``#``
comments.

Times are converted from their digits to whole nanoseconds (integer arithmetic; an exponent
through :class:`decimal.Decimal`), never through a float, so ``1700000000.123456789`` s is
1700000000123456789 ns. Blank lines are skipped. An empty, ``nan`` or ``inf`` value skips its
row (counted); a row with the wrong number of fields or a non-number is an error naming its line.

This is the line-by-line reader, the reference: an import reads a table once for all its
streams, in blocks (`.text_fast`, `fusionlog.io.replay.read_streams`), wherever that reads it
the same way, and comes here for the rest and for every error.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
import re
from collections.abc import Iterator, Sequence
from decimal import ROUND_HALF_EVEN, Context, Decimal, InvalidOperation
from pathlib import Path

from .fields import INT64_MAX, TIME_UNITS
from .series import Collector, Series, fail
from .source import MAX_TEXT_BYTES, bounded_lines, open_source

__all__ = [
    "DELIMITERS",
    "TUM_COLUMNS",
    "column_index",
    "read_text",
    "table_layout",
    "text_collector",
]

_CTX = Context(prec=80)
TUM_COLUMNS = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
# tried in this order when the delimiter is not given; "whitespace" splits on runs of blanks
DELIMITERS = {",": "comma", "\t": "tab", ";": "semicolon", "whitespace": "whitespace"}
_DECIMAL = re.compile(r"([+-]?)(\d*)(?:\.(\d*))?")
_SNIFF_LINES = 5


def column_index(source: Path, what: str, header: list[str], name: str, key: str) -> int:
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


def time_ns(text: str, unit: str) -> int | None:
    """Nanoseconds from the digits of a decimal number in ``unit``, rounded half to even;
    None for NaN/inf; ValueError for a non-number or a time beyond 64-bit nanoseconds."""
    s = text.strip()
    if not s:
        raise ValueError("empty")
    if "_" in s or not s.isascii():  # Python reads "1_000" and other scripts' digits
        raise ValueError("not a number")
    factor = TIME_UNITS[unit]
    m = _DECIMAL.fullmatch(s)
    if m and (m.group(2) or m.group(3)):
        sign, whole, frac = m.group(1), m.group(2) or "0", m.group(3) or ""
        scale = 10 ** len(frac)
        q, r = divmod(int(whole + frac) * factor, scale)  # ns = (q + r / scale), exactly
        if 2 * r > scale or (2 * r == scale and q % 2):
            q += 1
        ns = -q if sign == "-" else q
    else:
        try:
            d = Decimal(s)
        except InvalidOperation:
            raise ValueError("not a number") from None
        if not d.is_finite():
            return None
        try:
            ns = int(_CTX.multiply(d, factor).to_integral_value(rounding=ROUND_HALF_EVEN))
        except ArithmeticError:  # decimal.Overflow: beyond any clock
            raise ValueError("outside the range of 64-bit nanoseconds") from None
    if not -INT64_MAX - 1 <= ns <= INT64_MAX:
        raise ValueError("outside the range of 64-bit nanoseconds")
    return ns


def _number(text: str) -> float:
    s = text.strip()
    if not s:
        return math.nan  # an empty cell is a missing value: the row is skipped and counted
    if "_" in s or not s.isascii():  # float() reads "1_000" and other scripts' digits
        raise ValueError(s)
    return float(s)


class _Lines:
    """The file's lines that hold data (not blank, not ``#`` comments when ``comments``), with
    their 1-based line numbers in ``number``."""

    def __init__(self, f, comments: bool) -> None:
        self.f, self.comments, self.number = f, comments, 0

    def __iter__(self) -> Iterator[str]:
        for number, line in enumerate(self.f, 1):
            self.number = number  # read by the caller for its messages
            text = line.strip()
            if not text or (self.comments and text.startswith("#")):
                continue
            yield line


def _splitter(delimiter: str):
    if delimiter == "whitespace":
        return lambda line: line.split()
    return lambda line: next(
        csv.reader([line], delimiter=delimiter, skipinitialspace=True, strict=True)
    )


def _sniff(source: Path, what: str, lines: list[tuple[int, str]]) -> str:
    """The delimiter: the first that splits the sample lines into the same number (> 1) of
    fields, else the first that splits the first line (a bad row then gets its own error)."""
    splitting = []
    for delim in DELIMITERS:
        split = _splitter(delim)
        counts = [len(split(line)) for _, line in lines]
        if counts[0] > 1:
            if len(set(counts)) == 1:
                return delim
            splitting.append(delim)
    if splitting:
        return splitting[0]
    first = lines[0][1].strip()[:60]
    raise fail(
        source,
        what,
        f"line {lines[0][0]}: no delimiter (comma, tab, semicolon, whitespace) splits it into "
        f"columns ({first!r}); give delimiter",
    )


def _open(source: Path, what: str):
    """The table as text: a regular file of bounded size (`.source.open_source`)."""
    raw = open_source(source, what, MAX_TEXT_BYTES, "a text table")
    return io.TextIOWrapper(raw, encoding="utf-8-sig", newline="")  # closed by the caller


def table_layout(
    source: Path,
    what: str,
    sample: list[tuple[int, str]],
    delimiter: str | None,
    columns: Sequence[str] | None,
) -> tuple[str, list[str]]:
    """The delimiter (given, else sniffed from the `sample`: the first data lines with their
    numbers) and the header (the first sample line's fields, stripped, or `columns`): the one
    place both the line-by-line reader and `.text_fast` decide them."""
    if delimiter is None:
        delimiter = _sniff(source, what, sample)
    if columns is None:
        header = [c.strip() for c in _splitter(delimiter)(sample[0][1])]
    else:
        header = [c.strip() for c in columns]
    if len(header) < 2:
        name = delimiter if delimiter == "whitespace" else repr(delimiter)
        raise fail(
            source,
            what,
            f"delimiter {name} does not split line {sample[0][0]} into columns "
            f"({sample[0][1].strip()[:60]!r})",
        )
    return delimiter, header


def text_collector(source: Path, what: str, d: int) -> Collector:
    """The Collector of a table's rows (its notes and errors say "row", "line k")."""
    return Collector(source, what, d, False, "row", lambda k: f"line {k}", "empty, NaN or infinite")


def read_text(
    source: Path,
    *,
    values: Sequence[str],
    time: str | None,
    time_unit: str,
    what: str,
    delimiter: str | None = None,
    columns: Sequence[str] | None = None,
    fmt: str | None = None,
) -> Series:
    if fmt == "tum":
        columns, delimiter = TUM_COLUMNS, delimiter or "whitespace"
        time = time if time is not None else "timestamp"
    col = text_collector(source, what, len(values))
    with _open(source, what) as f:
        lines = _Lines(bounded_lines(f, MAX_TEXT_BYTES, source, what), comments=columns is not None)
        it = iter(lines)
        try:
            sample = []
            for line in it:
                sample.append((lines.number, line))
                if len(sample) == _SNIFF_LINES:
                    break
            if not sample:
                raise fail(
                    source, what, "no lines with data" if columns else "empty file (no header line)"
                )
            delimiter, header = table_layout(source, what, sample, delimiter, columns)
            split = _splitter(delimiter)
            name = delimiter if delimiter == "whitespace" else repr(delimiter)
            rows = sample[1:] if columns is None else sample
            tname = time if time is not None else "time"
            vcols = [column_index(source, what, header, v, "values") for v in values]
            tcol = column_index(
                source, what, header, tname, "time" if time is not None else "time (default)"
            )

            def numbered() -> Iterator[tuple[int, list[str]]]:
                for number, line in rows:
                    yield number, split(line)
                if delimiter == "whitespace":
                    for line in it:
                        yield lines.number, line.split()
                    return
                # one reader over the remaining lines (a reader per line costs 3x as much)
                opts = {"delimiter": delimiter, "skipinitialspace": True, "strict": True}
                for fields in csv.reader(it, **opts):
                    yield lines.number, fields

            for number, row in numbered():
                if len(row) != len(header):
                    given = "columns has" if columns is not None else "the header has"
                    raise fail(
                        source,
                        what,
                        f"line {number}: {len(row)} fields where {given} {len(header)} "
                        f"(delimiter {name})",
                    )
                try:
                    t = time_ns(row[tcol], time_unit)
                except ValueError as e:
                    cell = row[tcol].strip()[:40]
                    problem = "is empty" if not cell else f"{cell!r} is {e}"
                    raise fail(
                        source, what, f"line {number}: time column {header[tcol]!r} {problem}"
                    ) from None
                vals = []
                for c in vcols:
                    try:
                        vals.append(_number(row[c]))
                    except ValueError:
                        raise fail(
                            source,
                            what,
                            f"line {number}: column {header[c]!r}: {row[c].strip()[:40]!r} is not "
                            "a number",
                        ) from None
                col.add(number, t, vals)
        except csv.Error as e:
            raise fail(source, what, f"line {lines.number}: not valid CSV ({e})") from None
        except UnicodeDecodeError as e:
            raise fail(source, what, f"not UTF-8 text (byte {e.start}: {e.reason})") from None
    if col.seen == 0:
        raise fail(source, what, "no data rows" + (" after the header" if columns is None else ""))
    return col.finish()
