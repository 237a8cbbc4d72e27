"""Every stream of one text table read in one pass, in blocks, with pyarrow's CSV parser.

A 10^6-row CSV replay's import read its file once per stream (two sensors and the truth: three
times), line by line in Python (~45 s of its ~47 s, issue 34). Here the file is read once for
all the streams that name it, 8 MB at a time: pyarrow splits each block into the requested
columns (as text), pyarrow.compute checks and converts them, and each stream's rows go into its
:class:`~.series.Collector` as typed arrays (no Python object per row).

Only what the line-by-line reader (:func:`.text_source.read_text`) reads the same way is taken:
a one-character ASCII delimiter other than a space or a quote (not ``whitespace``, not TUM), no
quote character, NUL or lone carriage return anywhere, no ``#`` when comments are skipped
(``columns`` given), UTF-8; every cell of a requested column a plain decimal number: a time is
digits with an optional fraction (no exponent), a value may have an exponent or be empty,
``nan`` or ``inf`` (its row then skipped and counted, as there). For anything else, and for any
problem (a short row, a non-number, a negative time, two rows at one time, a file that grows),
the stream's entry is None: the line-by-line reader then reads it and says what is wrong,
naming the line, exactly as before.

Times are exact, as in `.text_source.time_ns`: ns = whole · 10^e + the fraction's first e
digits (e = 9 for seconds), rounded half to even on its other digits, in checked int64
arithmetic on the digit strings; never through a float. Values are pyarrow's string-to-double
cast (fast_float: correctly rounded, as Python's ``float``).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO, NamedTuple

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pcsv

from fusionlog.core.timing import TIME_UNITS
from fusionlog.errors import FusionlogError

from .series import Series
from .source import MAX_TEXT_BYTES, open_source
from .text_source import column_index, table_layout, text_collector

__all__ = ["TextRequest", "read_table_streams"]

_BLOCK = 8 << 20  # bytes parsed at once: a few 10^5 rows
_SNIFF_LINES = 5  # as the line-by-line reader's sample
_BOM = b"\xef\xbb\xbf"
# a time: sign, whole digits, fraction digits (at least one digit, checked after)
_TIME = r"^[ \t]*(?P<sign>[+-]?)(?P<whole>[0-9]*)(?:\.(?P<frac>[0-9]*))?[ \t]*$"
_FINITE = r"^[ \t]*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?[ \t]*$"
_MISSING = r"^[ \t]*(?:[+-]?(?:nan|inf|infinity))?[ \t]*$"  # case-insensitive; or empty


class TextRequest(NamedTuple):
    """One stream of a table: its name in messages, value columns, time column and unit."""

    what: str
    values: tuple[str, ...]
    time: str | None
    time_unit: str


class _NotFast(Exception):
    """The table is not read here: the line-by-line reader reads it."""


def read_table_streams(
    source: Path,
    delimiter: str | None,
    columns: Sequence[str] | None,
    requests: Sequence[TextRequest],
    block_bytes: int = _BLOCK,
) -> list[Series | None]:
    """Each request's Series from one pass over the table `source` (a CSV of `delimiter` and
    `columns` as in `read_text`) in blocks of about `block_bytes` (whole lines), or None where
    the line-by-line reader must read it."""
    try:
        collectors = _read(source, delimiter, columns, requests, block_bytes)
    except (_NotFast, FusionlogError, pa.ArrowException, ValueError, UnicodeDecodeError, OSError):
        return [None] * len(requests)
    out: list[Series | None] = []
    for i in range(len(collectors)):
        col, collectors[i] = collectors[i], None  # its rows freed once its Series is made
        try:  # two rows at one time: the error names the lines, which only that reader knows
            out.append(None if col.has_duplicates() else col.finish())
        except FusionlogError:  # no rows with finite values: the reader says so
            out.append(None)
    return out


def _head(raw: BinaryIO, comments: bool) -> tuple[list[tuple[int, str]], int]:
    """The first data lines with their numbers (the reader's sniffing sample) and the offset
    where the rows start (after the header line, or at the first data line)."""
    sample: list[tuple[int, str]] = []
    offset, start = 0, -1
    for number in range(1, 1 << 62):
        line = raw.readline(1 << 20)
        if not line or len(sample) == _SNIFF_LINES:
            break
        at, offset = offset, offset + len(line)
        if not line.endswith(b"\n") and len(line) == 1 << 20:
            raise _NotFast  # a megabyte without a line end
        if b"\r" in line.rstrip(b"\n")[:-1]:
            raise _NotFast  # a lone carriage return ends a line for the text reader only
        text = line[len(_BOM) :] if number == 1 and line.startswith(_BOM) else line
        text = text.decode("utf-8")
        if not text.strip() or (comments and text.strip().startswith("#")):
            continue
        sample.append((number, text))
        if start < 0:
            start = at if comments else offset
    if not sample:
        raise _NotFast
    return sample, start


def _blocks(raw: BinaryIO, start: int, comments: bool, size: int) -> Iterator[bytes]:
    """The table's bytes from `start` in blocks of whole lines, each checked for what only
    the line-by-line reader reads (module docstring)."""
    raw.seek(start)
    carry, total = b"", start
    while True:
        chunk = raw.read(size)
        total += len(chunk)
        if total > MAX_TEXT_BYTES:
            raise _NotFast  # grew while read: the reader stops with its error
        buf = carry + chunk
        cut = len(buf) if not chunk else buf.rfind(b"\n") + 1
        block, carry = buf[:cut], buf[cut:]
        if block:
            if b'"' in block or b"\x00" in block or block.count(b"\r") != block.count(b"\r\n"):
                raise _NotFast
            if comments and b"#" in block:
                raise _NotFast
            if not block.isascii():
                block.decode("utf-8")  # UnicodeDecodeError: not UTF-8 text, the reader says so
            yield block
        if not chunk:
            return


def _parse(block: bytes, delimiter: str, width: int, wanted: list[int]) -> dict[int, pa.Array]:
    """The `wanted` columns of a block's rows as text; pyarrow raises on a row whose field
    count is not `width`."""
    names = [f"f{i}" for i in range(width)]
    table = pcsv.read_csv(
        pa.BufferReader(block),
        read_options=pcsv.ReadOptions(
            column_names=names, use_threads=False, block_size=len(block) + 1
        ),  # fmt: skip
        parse_options=pcsv.ParseOptions(
            delimiter=delimiter, quote_char=False, double_quote=False, escape_char=False
        ),  # fmt: skip
        convert_options=pcsv.ConvertOptions(
            column_types={names[i]: pa.string() for i in wanted},
            include_columns=[names[i] for i in wanted],
            null_values=[],
            strings_can_be_null=False,
            quoted_strings_can_be_null=False,
        ),
    )
    return {i: table.column(names[i]).combine_chunks() for i in wanted}


def _values(cells: pa.Array) -> np.ndarray:
    """float64 of a column's cells: a decimal number (correctly rounded) or NaN for an empty,
    NaN or infinite cell (skipped by the Collector, as `text_source._number`'s NaN)."""
    finite = pc.match_substring_regex(cells, _FINITE)
    missing = pc.match_substring_regex(cells, _MISSING, ignore_case=True)
    if not pc.all(pc.or_(finite, missing)).as_py():
        raise _NotFast
    text = pc.if_else(finite, pc.ascii_trim_whitespace(cells), "nan")
    return pc.cast(text, pa.float64()).to_numpy(zero_copy_only=False)


def _digits(text: pa.Array) -> pa.Array:
    """int64 of digit strings ("" is 0); pyarrow raises beyond int64."""
    return pc.cast(pc.binary_join_element_wise("0", text, ""), pa.int64())


def _times_ns(cells: pa.Array, unit: str) -> np.ndarray:
    """int64 ns of decimal times in `unit`, exactly (module docstring), all >= 0."""
    e = len(str(TIME_UNITS[unit])) - 1  # factor 10^e
    m = pc.extract_regex(cells, _TIME)
    if m.null_count:
        raise _NotFast
    sign, whole, frac = (m.field(k) for k in ("sign", "whole", "frac"))
    if not pc.all(pc.greater(pc.add(pc.utf8_length(whole), pc.utf8_length(frac)), 0)).as_py():
        raise _NotFast  # "." or "": no digits
    q = pc.multiply_checked(_digits(whole), 10**e)
    if e:
        head = pc.utf8_slice_codeunits(pc.utf8_rpad(frac, width=e, padding="0"), 0, e)
        q = pc.add_checked(q, _digits(head))
    rest = pc.utf8_slice_codeunits(frac, e)  # the digits below a nanosecond
    first = pc.utf8_slice_codeunits(rest, 0, 1)
    beyond = pc.match_substring_regex(pc.utf8_slice_codeunits(rest, 1), "[1-9]")
    five = pc.equal(first, "5")
    odd = pc.equal(pc.bit_wise_and(q, 1), 1)
    up = pc.or_(pc.greater(first, "5"), pc.and_(five, pc.or_(beyond, odd)))  # half to even
    q = pc.add_checked(q, pc.cast(up, pa.int64()))
    ns = pc.if_else(pc.equal(sign, "-"), pc.negate_checked(q), q)
    if pc.any(pc.less(ns, 0)).as_py():
        raise _NotFast  # before 1970: the reader's error names the line
    return ns.to_numpy(zero_copy_only=False)


def _read(source: Path, delimiter: str | None, columns: Sequence[str] | None,
          requests: Sequence[TextRequest], block_bytes: int) -> list:  # fmt: skip
    what = requests[0].what
    with open_source(source, what, MAX_TEXT_BYTES, "a text table") as raw:
        comments = columns is not None
        sample, start = _head(raw, comments)
        delimiter, header = table_layout(source, what, sample, delimiter, columns)
        if len(delimiter) != 1 or not delimiter.isascii() or delimiter in ' "\r\n':
            raise _NotFast
        vcols = [[column_index(source, r.what, header, v, "values") for v in r.values]
                 for r in requests]  # fmt: skip
        tcols = [column_index(source, r.what, header, r.time or "time", "time") for r in requests]
        wanted = sorted({*tcols, *(c for v in vcols for c in v)})
        times = sorted({(c, r.time_unit) for c, r in zip(tcols, requests, strict=True)})
        collectors = [text_collector(source, r.what, len(r.values)) for r in requests]
        for block in _blocks(raw, start, comments, block_bytes):
            cells = _parse(block, delimiter, len(header), wanted)
            ns = {(c, u): _times_ns(cells[c], u) for c, u in times}
            vals = {c: _values(cells[c]) for c in {c for v in vcols for c in v}}
            for col, r, tc, vc in zip(collectors, requests, tcols, vcols, strict=True):
                col.add_rows(ns[tc, r.time_unit], np.stack([vals[c] for c in vc], axis=1))
    return collectors
