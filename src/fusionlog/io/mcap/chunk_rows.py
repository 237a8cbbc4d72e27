"""A chunk's messages as columns of offsets, found through its message indexes (issue 34).

`chunks.read_chunk` hands over a chunk's messages as mcap ``Message`` objects, one Python
object and one bytes copy per message, found by walking the records one by one: ~1 µs a
message, 10 s of a 10^6-instant log's evaluation (4·10^6 sensor and 7·10^6 estimate
messages). Every MCAP writer that indexes its chunks (the Rust writer fusionlog uses does)
follows each chunk with a MessageIndex record per channel: the offset of each of its messages
in the chunk's records. Those are read here as numpy arrays, and every message record they
point at is checked with numpy (opcode, length within the chunk, channel) — and the records
must tile the chunk: what lies between them is read record by record (schema and channel
records) and must hold no message. A chunk whose indexes do not pass, is compressed
differently, or has none is read by `chunks.read_chunk` as before (which reports what is
wrong); the rows are the same either way.

The chunk's CRC is checked (``validate_crc`` as mcap does) before any of its bytes are used.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.opcode import Opcode
from mcap.records import ChunkIndex, Message

from .chunks import (
    _CHUNK_HEAD,
    _MESSAGE_HEAD,
    _RECORD_HEAD,
    _U64,
    _crc_range,
    _damaged,
    _messages_only,
    one_line,
    read_chunk,
)

__all__ = ["Rows", "chunk_rows", "first_message", "message_rows"]

_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel_id, records length
_MESSAGE_FIXED = 22  # channel_id (2), sequence (4), log_time (8), publish_time (8)


@dataclass
class Rows:
    """Messages as columns: each one's channel, and where its data lies in ``raw``."""

    raw: bytes
    cid: np.ndarray
    start: np.ndarray
    length: np.ndarray

    def __len__(self) -> int:
        return len(self.cid)


def message_rows(messages: Sequence[Any]) -> Rows:
    """Rows of mcap ``Message`` objects (their data joined)."""
    datas = [m.data for m in messages]
    n = len(datas)
    cid = np.fromiter([m.channel_id for m in messages], np.int64, n)
    length = np.fromiter(map(len, datas), np.int64, n)
    start = np.zeros(n, np.int64)
    np.cumsum(length[:-1], out=start[1:])
    return Rows(b"".join(datas), cid, start, length)


def chunk_rows(f: BinaryIO, path: Path, ci: ChunkIndex, only: set[int] | None = None) -> Rows:
    """The messages of the chunk ``ci`` (of the channels ``only``, if given) in file order, as
    `read_chunk` finds them; see the module docstring."""
    rows = None
    if ci.message_index_offsets and ci.compression == "":
        f.seek(ci.chunk_start_offset)
        buf = f.read(ci.chunk_length + ci.message_index_length)
        try:
            data = _chunk_data(buf, ci)
        except Exception as e:
            raise _damaged(
                path, f"corrupt MCAP chunk at byte {ci.chunk_start_offset} ({one_line(e)})"
            ) from e
        if data is not None:
            rows = _indexed(data, memoryview(buf)[ci.chunk_length :], only)
    return rows if rows is not None else message_rows(read_chunk(f, path, ci, only))


def _chunk_data(buf: bytes, ci: ChunkIndex) -> bytes | None:
    """The records of the uncompressed chunk record at the start of ``buf``, CRC checked;
    None if it is compressed after all (mcap's reader then reads it)."""
    op, length, _, _, _, ucrc, clen = _CHUNK_HEAD.unpack_from(buf, 0)
    at = _CHUNK_HEAD.size + clen
    (dlen,) = _U64.unpack_from(buf, at)
    at += _U64.size
    if op != Opcode.CHUNK or 9 + length != ci.chunk_length or at + dlen > ci.chunk_length:
        raise ValueError("chunk index does not point at a chunk")
    if clen:
        return None
    data = buf[at : at + dlen]
    if ucrc and zlib.crc32(data) != ucrc:
        raise ValueError(f"chunk CRC {zlib.crc32(data):08x} where the file records {ucrc:08x}")
    return data


def _indexed(data: bytes, index: memoryview, only: set[int] | None) -> Rows | None:
    """The rows of the messages the index records point at, checked; None where they are not
    every message of the chunk (or of ``only``'s channels), one by one and record by record."""
    offsets, cids = [], []
    pos, end = 0, len(index)
    while pos < end:
        if pos + _INDEX_HEAD.size > end:
            return None
        op, length, cid, rlen = _INDEX_HEAD.unpack_from(index, pos)
        if op != Opcode.MESSAGE_INDEX or length != 6 + rlen or rlen % 16 or pos + 9 + length > end:
            return None
        if only is None or cid in only:
            pairs = np.frombuffer(index, "<u8", rlen // 8, pos + _INDEX_HEAD.size)
            offsets.append(pairs[1::2])
            cids.append(np.full(rlen // 16, cid, np.int64))
        pos += 9 + length
    if not offsets:
        return Rows(data, *(np.zeros(0, np.int64) for _ in range(3)))
    off = np.concatenate(offsets).astype(np.int64)
    cid = np.concatenate(cids)
    order = np.argsort(off, kind="stable")
    off, cid = off[order], cid[order]
    u8 = np.frombuffer(data, np.uint8)
    size = len(u8)
    if len(off) and (off[0] < 0 or off[-1] + 9 + _MESSAGE_FIXED > size):
        return None
    head = u8[off[:, None] + np.arange(11)]  # opcode, record length (8), channel id (2)
    length = np.ascontiguousarray(head[:, 1:9]).view("<u8")[:, 0]
    channel = np.ascontiguousarray(head[:, 9:11]).view("<u2")[:, 0]
    if not ((head[:, 0] == Opcode.MESSAGE).all() and (channel == cid).all()):
        return None
    if not ((length >= _MESSAGE_FIXED) & (length <= size)).all():
        return None
    stop = off + 9 + length.astype(np.int64)
    if (stop > size).any() or (off[1:] < stop[:-1]).any():  # beyond the chunk, overlapping
        return None
    if only is None and not _only_other_records(data, off, stop):
        return None
    start = off + 9 + _MESSAGE_FIXED
    return Rows(data, cid, start, stop - start)


def _only_other_records(data: bytes, off: np.ndarray, stop: np.ndarray) -> bool:
    """Whether the bytes around the messages at [off, stop) are whole records none of which is
    a message (the chunk's schema and channel records)."""
    starts = np.concatenate([[0], stop])
    ends = np.concatenate([off, [len(data)]])
    for a, b in zip(starts[ends > starts].tolist(), ends[ends > starts].tolist(), strict=True):
        if _messages_only(data[a:b]) != []:  # a message the index misses, or no records
            return False
    return True


#: Bytes read at a time while checking a chunk's CRC without holding it (`first_message`).
_CRC_STEP = 1 << 16


def first_message(f: BinaryIO, path: Path, ci: ChunkIndex, cids: set[int]) -> Message | None:
    """The first message (in file order) of the channels `cids` in the uncompressed, indexed
    chunk `ci`, read alone: its offset from the first entry of each channel's message index,
    the chunk's CRC checked a stretch at a time. No other message is read or kept (issue 34:
    reading the whole chunk as mcap ``Message`` objects for one message held ~5 MB for a
    1 MiB chunk, growing with a short log). None where the chunk is compressed, not indexed,
    or its index does not point at such a message: then `read_chunk` reads it (and says what
    is wrong)."""
    if ci.compression != "" or not ci.message_index_offsets:
        return None
    first = None
    for cid in sorted(cids & set(ci.message_index_offsets)):
        f.seek(ci.message_index_offsets[cid])
        head = f.read(_INDEX_HEAD.size + 16)  # the record's head and its first (time, offset)
        if len(head) < _INDEX_HEAD.size:
            return None
        op, length, channel, rlen = _INDEX_HEAD.unpack_from(head)
        if op != Opcode.MESSAGE_INDEX or channel != cid or length != 6 + rlen or rlen % 16:
            return None
        if rlen and len(head) == _INDEX_HEAD.size + 16:
            at = _U64.unpack_from(head, _INDEX_HEAD.size + 8)[0]
            first = at if first is None else min(first, at)
    if first is None:
        return None
    start = ci.chunk_start_offset
    f.seek(start)
    op, length, _, _, _, ucrc, clen = _CHUNK_HEAD.unpack(f.read(_CHUNK_HEAD.size))
    if op != Opcode.CHUNK or 9 + length != ci.chunk_length or clen:
        return None
    (dlen,) = _U64.unpack(f.read(_U64.size))
    data_at = start + _CHUNK_HEAD.size + _U64.size
    if data_at + dlen > start + ci.chunk_length or first + 9 + _MESSAGE_FIXED > dlen:
        return None
    try:
        crc = _crc_range(f, data_at, data_at + dlen, 0, _CRC_STEP)
        if ucrc and crc != ucrc:
            raise ValueError(f"chunk CRC {crc:08x} where the file records {ucrc:08x}")
    except (ValueError, EOFError) as e:
        raise _damaged(path, f"corrupt MCAP chunk at byte {start} ({one_line(e)})") from e
    f.seek(data_at + first)
    head = f.read(9 + _MESSAGE_FIXED)
    op, length = _RECORD_HEAD.unpack_from(head)
    cid, seq, log_time, publish_time = _MESSAGE_HEAD.unpack_from(head, 9)
    if op != Opcode.MESSAGE or length < _MESSAGE_FIXED or first + 9 + length > dlen:
        return None
    if cid not in cids:
        return None
    return Message(cid, log_time, f.read(length - _MESSAGE_FIXED), publish_time, seq)
