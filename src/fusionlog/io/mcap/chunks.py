"""MCAP at the record level: opening the container, reading chunks, checking the CRCs.

This module and :mod:`.chunk_rows` (its indexed fast path) are the only ones that use
``mcap``'s unexported internals (``breakup_chunk``, ``get_chunk_data_stream``,
``Message.read``, ``MessageIndex.read``, ``ReadDataStream``, the record opcodes); they
are pinned in pyproject.toml to the mcap versions tested (a keyword of these functions has
changed name across versions).

Why not ``SeekingReader.iter_messages``: with ``log_time_order=False`` mcap 1.6 reads and
decompresses *every* chunk into its queue before yielding the first message (unbounded
memory), and log-time order would interleave the blocks of runs. So the reader walks the chunk
indexes itself, one chunk in memory at a time.

**Integrity.** An MCAP file carries three kinds of CRC-32 (zlib's polynomial): each chunk's
(of its uncompressed records), the data section's (every byte from the leading magic up to the
DataEnd record) and the summary's. All three are checked where the file has them (a CRC of 0
means "not computed"), so that one changed byte anywhere is an error, not a silently different
model or number:

- the summary CRC when the file is opened (the summary is small);
- the chunk CRCs when a chunk is read (as mcap does with ``validate_crc``);
- the data-section CRC when the file is opened, *without reading the chunks' data a second
  time*: the CRC of the data section is composed from the bytes outside the chunks' data
  (header, metadata, schemas, message indexes, each chunk's own header, all read here) and,
  for each uncompressed chunk, its recorded CRC and length (``crc32_combine``, the GF(2)
  arithmetic of zlib's ``crc32_combine``). The chunk's data is then checked against that same
  recorded CRC when it is read, so every byte is covered by one check or the other. Compressed
  chunks, and chunks without a CRC, are read and hashed here (their stored bytes are not what
  their CRC covers). A file without an index is scanned from end to end when opened anyway;
  mcap's ``StreamReader(validate_crcs=True)`` checks its CRCs during that scan.

  Measured on a 168 MB sensors file (200 000 runs, 1 MB chunks) in the page cache: opening with
  this check costs ~2 ms more, where a plain ``zlib.crc32`` pass over the file costs ~60 ms
  (+25 % of reading the whole file, +50 % of reading ``/truth`` alone through the message
  indexes).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

from fusionlog.errors import DamagedFile, FusionlogError

__all__ = [
    "MAGIC",
    "CRCMismatch",
    "Container",
    "crc32_combine",
    "linear_batches",
    "one_line",
    "open_container",
    "open_error",
    "read_chunk",
    "records",
]

MAGIC = b"\x89MCAP0\r\n"

#: Messages (at most) and bytes (about) per batch when a file without index is read linearly.
_LINEAR_BATCH = 8192
_LINEAR_BYTES = 1 << 20

# Record sizes from the MCAP specification: opcode (1), record length (8), fields.
_FOOTER = struct.Struct("<BQQQI")  # summary_start, summary_offset_start, summary_crc
_DATA_END = struct.Struct("<BQI")  # data_section_crc
_CHUNK_HEAD = struct.Struct("<BQQQQII")  # start, end time, uncompressed size, crc, compression
_U64 = struct.Struct("<Q")
_READ = 1 << 20  # bytes per read when hashing a range

# What mcap raises on bytes it cannot parse.
_PARSE_ERRORS = (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError)


def one_line(e: BaseException) -> str:
    """Exception text for a one-line user message (library messages may contain newlines)."""
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def open_error(path: Path, e: OSError) -> FusionlogError:
    if isinstance(e, FileNotFoundError):
        return FusionlogError(f"{path}: no such file")
    if isinstance(e, IsADirectoryError):
        return FusionlogError(f"{path}: is a directory, not an MCAP file")
    if isinstance(e, PermissionError):
        return FusionlogError(f"{path}: permission denied")
    return FusionlogError(f"{path}: cannot read: {e.strerror or e}")


def _damaged(path: Path, what: str) -> DamagedFile:
    return DamagedFile(f"{path}: {what}", path)


# --------------------------------------------------------------------------------------------
# CRC-32 arithmetic
# --------------------------------------------------------------------------------------------

_POLY = 0xEDB88320  # zlib's CRC-32 polynomial, reflected


def _multmodp(a: int, b: int) -> int:
    """a(x) * b(x) modulo the CRC polynomial (reflected bit order; a != 0), as zlib does."""
    m = 1 << 31
    p = 0
    while True:
        if a & m:
            p ^= b
            if not a & (m - 1):
                return p
        m >>= 1
        b = (b >> 1) ^ _POLY if b & 1 else b >> 1


def _x2n_table() -> list[int]:
    table = [1 << 30]  # x^1
    for _ in range(31):
        table.append(_multmodp(table[-1], table[-1]))  # x^(2^k)
    return table


_X2N = _x2n_table()


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """``zlib.crc32(a + b)`` from ``crc1 = zlib.crc32(a)``, ``crc2 = zlib.crc32(b)`` and
    ``len2 = len(b)``: crc1 shifted by len2 zero bytes (times x^(8 len2) mod P) xor crc2.
    About 30 µs, whatever len2."""
    p = 1 << 31  # x^0
    n, k = len2, 3  # x^(8 len2) = product of x^(2^k) over the bits of len2, shifted by 3
    while n:
        if n & 1:
            p = _multmodp(_X2N[k & 31], p)
        n >>= 1
        k += 1
    return _multmodp(p, crc1) ^ crc2


class CRCMismatch(ValueError):
    """A recorded CRC-32 differs from the one of the bytes it covers."""

    def __init__(self, what: str, recorded: int, computed: int) -> None:
        super().__init__(
            f"{what} CRC {computed:08x} where the file records {recorded:08x}: "
            "bytes changed after it was written"
        )


def _crc_range(f: BinaryIO, start: int, end: int, crc: int, step: int = _READ) -> int:
    f.seek(start)
    left = end - start
    while left > 0:
        data = f.read(min(left, step))
        if not data:
            raise EOFError(f"file ends at byte {end - left}")
        crc = zlib.crc32(data, crc)
        left -= len(data)
    return crc


# --------------------------------------------------------------------------------------------
# Opening
# --------------------------------------------------------------------------------------------


@dataclass
class Container:
    """What opening an MCAP file learns: records of the summary (or of a linear scan when the
    file has no usable index) and where the chunks are."""

    library: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    counts: dict[int, int] = field(default_factory=dict)  # messages per channel
    #: (chunk index, the channels it holds or None if unknown), in file order
    chunks: list[tuple[ChunkIndex, set[int] | None]] = field(default_factory=list)
    linear: bool = False  # no usable index: read the records from the start


def read_metadata(path: Path, name: str) -> dict[str, str]:
    """The metadata record `name` of the MCAP file at `path` (opened and checked before), read
    again through its summary's index (the whole file where it has none); {} if absent."""
    with open(path, "rb") as f:
        for m in SeekingReader(f).iter_metadata():
            if m.name == name:
                return dict(m.metadata)
    return {}


def open_container(f: BinaryIO, path: Path) -> Container:
    """Open and check an MCAP file: magic bytes, footer, CRCs, summary or linear scan.

    Raises FusionlogError for a file that is not MCAP, DamagedFile for a damaged one.
    """
    size = os.fstat(f.fileno()).st_size
    head = f.read(len(MAGIC))
    if head != MAGIC:
        what = "empty file" if size == 0 else "does not start with the MCAP magic bytes"
        raise FusionlogError(f"{path}: not an MCAP file ({what})")
    f.seek(max(0, size - len(MAGIC)))
    if size < 2 * len(MAGIC) or f.read(len(MAGIC)) != MAGIC:
        raise _damaged(
            path,
            "truncated MCAP file (it ends before its footer; the writer was "
            "interrupted or the copy is incomplete)",
        )
    out = Container()
    try:
        data_end = _check_summary_crc(f, size)
    except CRCMismatch as e:
        raise _damaged(path, f"corrupt MCAP file ({e})") from e
    except _PARSE_ERRORS as e:
        raise _damaged(path, f"corrupt MCAP file (footer unreadable: {one_line(e)})") from e
    try:
        f.seek(0)
        reader = SeekingReader(f)
        out.library = reader.get_header().library
        summary = reader.get_summary()
        if summary is not None:
            out.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    except _PARSE_ERRORS as e:
        msg = f"corrupt MCAP file (footer or summary unreadable: {one_line(e)})"
        raise _damaged(path, msg) from e

    stats = summary.statistics if summary is not None else None
    complete = (
        summary is not None
        and stats is not None
        and all(cid in summary.channels for cid in stats.channel_message_counts)
        and all(c.schema_id in summary.schemas for c in summary.channels.values() if c.schema_id)
        and (stats.message_count == 0 or len(summary.chunk_indexes) > 0)
    )
    if not complete:
        # No usable index (written without summary/statistics/chunks): one linear scan, which
        # checks the data-section and chunk CRCs on the way.
        out.linear = True
        _scan_linear(f, path, out)
        return out
    assert summary is not None and stats is not None
    out.schemas, out.channels = summary.schemas, summary.channels
    out.counts = dict(stats.channel_message_counts)
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    for ci in indexes:
        ids = set(ci.message_index_offsets) if ci.message_index_offsets else None
        out.chunks.append((ci, ids))
    try:
        _check_data_crc(f, data_end, indexes)
    except CRCMismatch as e:
        raise _damaged(path, f"corrupt MCAP file ({e})") from e
    except _PARSE_ERRORS as e:
        raise _damaged(path, f"corrupt MCAP file ({one_line(e)})") from e
    return out


def _check_summary_crc(f: BinaryIO, size: int) -> int | None:
    """Check the footer's summary CRC; return where the data section's DataEnd record starts
    (None if the file has no summary, whose DataEnd a linear scan checks instead)."""
    footer_at = size - len(MAGIC) - _FOOTER.size
    f.seek(footer_at)
    op, length, summary_start, _, summary_crc = _FOOTER.unpack(f.read(_FOOTER.size))
    if op != Opcode.FOOTER or length != _FOOTER.size - 9:
        raise McapError("no footer record at the end of the file")
    if summary_start > footer_at or 0 < summary_start < len(MAGIC) + _DATA_END.size:
        raise McapError(f"the footer puts the summary at byte {summary_start}, outside the file")
    if summary_crc:
        # from the summary's start through the footer's summary_offset_start field
        crc = _crc_range(f, summary_start or footer_at, footer_at + _FOOTER.size - 4, 0)
        if crc != summary_crc:
            raise CRCMismatch("summary", summary_crc, crc)
    return summary_start - _DATA_END.size if summary_start else None


def _check_data_crc(f: BinaryIO, data_end: int | None, chunks: list[ChunkIndex]) -> None:
    """Check the data-section CRC, composing each uncompressed chunk's data from its recorded
    CRC instead of reading it (see the module docstring)."""
    if data_end is None or data_end < len(MAGIC):
        raise McapError("no data end record before the summary")
    f.seek(data_end)
    op, length, recorded = _DATA_END.unpack(f.read(_DATA_END.size))
    if op != Opcode.DATA_END or length != 4:
        raise McapError("no data end record before the summary")
    if not recorded:
        return  # the writer computed none
    crc, pos = 0, 0
    for ci in chunks:
        start = ci.chunk_start_offset
        if start < pos or start + ci.chunk_length > data_end:
            raise McapError(f"chunk index points at byte {start}, outside the data section")
        crc = _crc_range(f, pos, start, crc)
        f.seek(start)
        head = f.read(_CHUNK_HEAD.size)
        op, length, _, _, usize, ucrc, clen = _CHUNK_HEAD.unpack(head)
        rest = f.read(clen + _U64.size)
        (dlen,) = _U64.unpack_from(rest, clen)
        data_at = start + len(head) + len(rest)
        if op != Opcode.CHUNK or data_at + dlen > start + 9 + length:
            raise McapError(f"no chunk record at byte {start}, where the chunk index says")
        crc = zlib.crc32(rest, zlib.crc32(head, crc))
        if clen == 0 and ucrc and usize == dlen:
            crc = crc32_combine(crc, ucrc, dlen)  # the data is checked against ucrc when read
        else:
            crc = _crc_range(f, data_at, data_at + dlen, crc)
        pos = data_at + dlen
    crc = _crc_range(f, pos, data_end, crc)
    if crc != recorded:
        raise CRCMismatch("data section", recorded, crc)


def _scan_linear(f: BinaryIO, path: Path, out: Container) -> None:
    f.seek(0)
    try:
        for rec in StreamReader(f, validate_crcs=True).records:
            if isinstance(rec, Message):
                out.counts[rec.channel_id] = out.counts.get(rec.channel_id, 0) + 1
            elif isinstance(rec, Channel):
                out.channels[rec.id] = rec
            elif isinstance(rec, Schema):
                out.schemas[rec.id] = rec
            elif isinstance(rec, Metadata):
                out.metadata[rec.name] = dict(rec.metadata)
    except _PARSE_ERRORS as e:
        raise _damaged(path, f"corrupt MCAP file ({one_line(e)})") from e
    unknown = set(out.counts) - set(out.channels)
    if unknown:
        raise FusionlogError(f"{path}: messages on undeclared channels {sorted(unknown)}")


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def read_chunk(
    f: BinaryIO, path: Path, ci: ChunkIndex, only: set[int] | None = None
) -> list[Message]:
    """One chunk's messages, via mcap's own record reader (one chunk in memory at a time);
    with ``only``, just those channels' messages, found through the chunk's message indexes
    (every record is still mcap's to read).

    CRCs are validated: uncompressed chunks and zstd frames carry no checksum of their own,
    so flipped bytes in a chunk would otherwise decode as wrong numbers.
    """
    f.seek(ci.chunk_start_offset)
    try:
        chunk = next(iter(StreamReader(f, skip_magic=True, emit_chunks=True).records))
        if not isinstance(chunk, Chunk):
            raise ValueError("chunk index does not point at a chunk")
        if only is None:
            stream, size = get_chunk_data_stream(chunk, validate_crc=True)
            msgs = _messages_only(stream.read(size))
            if msgs is not None:
                return msgs
            recs = breakup_chunk(chunk, validate_crc=True)
            return [r for r in recs if isinstance(r, Message)]
        offsets: list[int] = []
        for cid in only:
            f.seek(ci.message_index_offsets[cid])
            index = next(iter(StreamReader(f, skip_magic=True).records))
            if not isinstance(index, MessageIndex) or index.channel_id != cid:
                raise ValueError(f"no message index of channel {cid} where the index says")
            offsets.extend(o for _, o in index.records)
        stream, size = get_chunk_data_stream(chunk, validate_crc=True)
        raw = stream.read(size)
        msgs = _indexed_messages(raw, sorted(offsets), only)
        if msgs is not None:
            return msgs
        data = BytesIO(raw)
        records = ReadDataStream(data)
        out = []
        for o in sorted(offsets):  # file order
            data.seek(o)
            if records.read1() != Opcode.MESSAGE:
                raise ValueError(f"message index points at offset {o}, not at a message")
            msg = Message.read(records, records.read8())
            if msg.channel_id not in only:
                raise ValueError(f"message index points at offset {o}, another channel")
            out.append(msg)
        return out
    except Exception as e:
        raise _damaged(
            path, f"corrupt MCAP chunk at byte {ci.chunk_start_offset} ({one_line(e)})"
        ) from e


_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")


def _messages_only(data: bytes) -> list[Message] | None:
    """The messages of a chunk's (checked) records, read as ``breakup_chunk`` reads them: one
    `struct` call per message instead of mcap's five stream reads; its schema and channel
    records read by mcap, other records skipped. None where a record does not end where its
    length says, which mcap's reader then reads (and reports) as before."""
    out = []
    pos, end = 0, len(data)
    record, head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    message, others = Opcode.MESSAGE, {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel}
    while pos < end:
        if pos + 9 > end:
            return None
        op, length = record(data, pos)
        body, pos = pos + 9, pos + 9 + length
        if pos > end:
            return None
        if op == message:
            if length < 22:
                return None
            cid, seq, log_time, publish_time = head(data, body)
            out.append(Message(cid, log_time, data[body + 22 : pos], publish_time, seq))
        elif op in others:
            stream = ReadDataStream(BytesIO(data[body:pos]))
            try:
                others[op].read(stream)
            except Exception:  # noqa: BLE001 - mcap's reader will say what it is
                return None
            if stream.count != length:
                return None
    return out


def _indexed_messages(data: bytes, offsets: list[int], only: set[int]) -> list[Message] | None:
    """The messages at `offsets` of a chunk's records (``read_chunk``'s indexed read), or None
    where one is not a message of `only` that ends within the chunk (then read by mcap)."""
    out = []
    end = len(data)
    record, head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    for o in offsets:
        if o < 0 or o + 31 > end:
            return None
        op, length = record(data, o)
        body, stop = o + 9, o + 9 + length
        if op != Opcode.MESSAGE or length < 22 or stop > end:
            return None
        cid, seq, log_time, publish_time = head(data, body)
        if cid not in only:
            return None
        out.append(Message(cid, log_time, data[body + 22 : stop], publish_time, seq))
    return out


def linear_batches(f: BinaryIO, path: Path, cids: set[int]) -> Iterator[list[Message]]:
    """The messages of ``cids`` in a file without index, read from its start in batches
    (at most _LINEAR_BATCH messages or _LINEAR_BYTES bytes: memory as with chunks)."""
    f.seek(0)
    recs = iter(StreamReader(f).records)
    batch: list[Message] = []
    size = 0
    while True:
        try:
            rec = next(recs, None)
        except _PARSE_ERRORS as e:
            raise _damaged(path, f"corrupt MCAP file ({one_line(e)})") from e
        if isinstance(rec, Message) and rec.channel_id in cids:
            batch.append(rec)
            size += len(rec.data)
        if rec is None or len(batch) == _LINEAR_BATCH or size >= _LINEAR_BYTES:
            if batch:
                yield batch
            if rec is None:
                return
            batch, size = [], 0


def records(f: BinaryIO) -> Iterator[object]:
    """Every record from the start of ``f``, chunks split, CRCs checked (for reading a damaged
    file as far as it goes); raises whatever mcap raises at the first damage."""
    return iter(StreamReader(f, validate_crcs=True).records)
