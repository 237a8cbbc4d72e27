"""MCAP reading and writing for fusionlog's sensor and estimate streams.

The file format is the contract in DESIGN.md ("MCAP files"): message encoding ``protobuf`` with the
schemas embedded as a FileDescriptorSet built at runtime, so any MCAP + protobuf reader (the
``mcap`` package with ``mcap-protobuf-support``, Rerun's ``rerun mcap convert``) decodes the files
without fusionlog. Two message types, both in the proto3 package ``fusionlog``::

    message Block         { uint32 step = 1; double time = 2; uint32 run_offset = 3;
                            uint32 runs = 4; uint32 dim = 5; repeated double values = 6; }
    message EstimateBlock { uint32 step = 1; double time = 2; uint32 run_offset = 3;
                            uint32 runs = 4; uint32 dim = 5; repeated double mean = 6;
                            repeated double covariance = 7; }

``values`` is (runs, dim) and ``mean`` is (runs, n), row-major; ``covariance`` is (n, n) when it is
the same for every run of the message and (runs, n, n) otherwise. NaN in ``values`` is a missing
measurement. ``log_time`` = ``publish_time`` = round(time * 1e9) ns.

**Writing order (what this module relies on to read with bounded memory).** Runs are split into
contiguous blocks starting at run 0 (``run_offset`` = 0, r0, r0 + r1, ...). For each block of runs,
for each step k = 0..K, for each topic, exactly one message. Thus all messages of one block are
contiguous in the file, so a reader can assemble a block of runs from one sequential pass and
then forget it. Inside a block the order of steps and topics does not matter to the reader.
McapWriter enforces this order; McapFile checks it and raises FusionlogError if a file breaks it.

Speed: messages are encoded and decoded here on the protobuf wire format directly (varint
scalars, packed doubles straight from/to ``ndarray`` bytes) instead of through protobuf message
classes, whose per-element handling of repeated fields costs several times more. The reader
decodes each chunk at once: its messages grouped by channel and length, each group checked
against the tag and length bytes of its first message and its fields read as numpy columns, so
that after mcap has split the chunk into records no Python runs per message. It walks the
chunks itself, because ``SeekingReader.iter_messages(log_time_order=False)``
in mcap 1.6 reads and decompresses *every* chunk into its queue before yielding the first
message (unbounded memory), and log-time order would interleave the blocks of runs.
"""

from __future__ import annotations

import math
import operator
import os
import re
import secrets
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

import foxglove
import numpy as np
from foxglove.mcap import MCAPCompression, MCAPWriteOptions, MCAPWriter
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

from fusionlog.errors import FusionlogError

__all__ = [
    "ESTIMATE_SCHEMA",
    "SENSOR_SCHEMA",
    "McapFile",
    "McapWriter",
    "decode_message",
    "encode_estimate_message",
    "encode_values_message",
    "file_descriptor_set",
    "protobuf_classes",
    "recover",
]

SENSOR_SCHEMA = "fusionlog.Block"
ESTIMATE_SCHEMA = "fusionlog.EstimateBlock"
PROTO_FILE = "fusionlog/blocks.proto"

VALUES = "values"
ESTIMATE = "estimate"

_MAGIC = b"\x89MCAP0\r\n"
_UINT32_MAX = 2**32 - 1

_F64 = struct.Struct("<d")
_F8 = np.dtype("<f8")


# --------------------------------------------------------------------------------------------
# Schema
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The proto3 file holding both message types, built without protoc."""
    fdp = descriptor_pb2.FileDescriptorProto(name=PROTO_FILE, package="fusionlog", syntax="proto3")
    F = descriptor_pb2.FieldDescriptorProto
    header = [
        ("step", 1, F.TYPE_UINT32),
        ("time", 2, F.TYPE_DOUBLE),
        ("run_offset", 3, F.TYPE_UINT32),
        ("runs", 4, F.TYPE_UINT32),
        ("dim", 5, F.TYPE_UINT32),
    ]
    for name, payload in (("Block", ["values"]), ("EstimateBlock", ["mean", "covariance"])):
        m = fdp.message_type.add(name=name)
        for fname, number, ftype in header:
            m.field.add(name=fname, number=number, type=ftype, label=F.LABEL_OPTIONAL)
        for i, fname in enumerate(payload):
            m.field.add(name=fname, number=6 + i, type=F.TYPE_DOUBLE, label=F.LABEL_REPEATED)
    return fdp


def file_descriptor_set() -> bytes:
    """Serialized FileDescriptorSet embedded as the schema data of both schemas."""
    return descriptor_pb2.FileDescriptorSet(file=[_file_descriptor()]).SerializeToString()


@lru_cache(maxsize=1)
def protobuf_classes() -> tuple[type, type]:
    """Official protobuf classes (Block, EstimateBlock) for tests and third-party style checks."""
    pool = descriptor_pool.DescriptorPool()
    pool.Add(_file_descriptor())
    return (
        message_factory.GetMessageClass(pool.FindMessageTypeByName(SENSOR_SCHEMA)),
        message_factory.GetMessageClass(pool.FindMessageTypeByName(ESTIMATE_SCHEMA)),
    )


# --------------------------------------------------------------------------------------------
# Wire encoding
# --------------------------------------------------------------------------------------------

_SMALL_VARINTS = [bytes([i]) for i in range(128)]


def _varint(value: int) -> bytes:
    if value < 0x80:
        return _SMALL_VARINTS[value]
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _encode(
    step: int, time: float, run_offset: int, runs: int, dim: int, payloads: Sequence[bytes]
) -> bytes:
    # Same bytes as SerializeToString of the official class: fields in number order and,
    # like every proto3 writer, zero scalars and empty repeated fields left out.
    parts: list[bytes] = []
    if step:
        parts += (b"\x08", _varint(step))
    t = _F64.pack(time)
    if t != b"\x00" * 8:  # -0.0 has a set sign bit and is written, as protobuf does
        parts += (b"\x11", t)
    if run_offset:
        parts += (b"\x18", _varint(run_offset))
    if runs:
        parts += (b"\x20", _varint(runs))
    if dim:
        parts += (b"\x28", _varint(dim))
    for tag, payload in zip((b"\x32", b"\x3a"), payloads, strict=False):
        if payload:
            parts += (tag, _varint(len(payload)), payload)
    return b"".join(parts)


def encode_values_message(
    step: int, time: float, run_offset: int, values: np.ndarray
) -> tuple[bytes, int, int]:
    """Wire bytes of one ``fusionlog.Block``; returns (data, runs, dim)."""
    v = np.ascontiguousarray(values, dtype="<f8")
    if v.ndim != 2 or v.shape[0] < 1:
        raise ValueError(f"values must have shape (runs >= 1, dim), got {v.shape}")
    runs, dim = v.shape
    return _encode(step, time, run_offset, runs, dim, (v.tobytes(),)), runs, dim


def encode_estimate_message(
    step: int, time: float, run_offset: int, mean: np.ndarray, cov: np.ndarray
) -> tuple[bytes, int, int]:
    """Wire bytes of one ``fusionlog.EstimateBlock``; returns (data, runs, n)."""
    m = np.ascontiguousarray(mean, dtype="<f8")
    c = np.ascontiguousarray(cov, dtype="<f8")
    if m.ndim != 2 or m.shape[0] < 1:
        raise ValueError(f"mean must have shape (runs >= 1, n), got {m.shape}")
    runs, n = m.shape
    if c.shape not in ((n, n), (runs, n, n)):
        raise ValueError(f"cov must have shape ({n}, {n}) or ({runs}, {n}, {n}), got {c.shape}")
    return _encode(step, time, run_offset, runs, n, (m.tobytes(), c.tobytes())), runs, n


# --------------------------------------------------------------------------------------------
# Wire decoding
# --------------------------------------------------------------------------------------------

# Actions of a wire key (field number << 3 | wire type) in a layout.
_A_STEP, _A_RUN_OFFSET, _A_RUNS, _A_DIM, _A_TIME, _A_P1, _A_P2 = range(7)
_INT_FIELDS = ("step", "run_offset", "runs", "dim")

Decoded = tuple[int, float, int, int, int, Any, Any]
"""(step, time, run_offset, runs, dim, payload1, payload2); payloads are bytes-like, LE doubles."""


class _WireError(Exception):
    """Malformed protobuf bytes (turned into a FusionlogError naming file and topic)."""


@dataclass(frozen=True)
class _Layout:
    """How to decode one schema: kind, a map from wire key to action, optional fast path."""

    kind: str
    keys: dict[int, int]
    fast: re.Pattern[bytes] | None = None
    p1_tag: int = -1
    p2_tag: int = -1


_VARINT_RE = rb"([\x80-\xff]{0,9}[\x00-\x7f])"


def _fast_pattern(numbers: dict[str, int], payload: list[str]) -> re.Pattern[bytes] | None:
    """Regex for the canonical encoding (fields in number order, one-byte tags), else None.

    The regex engine runs in C, so matching the five scalars this way costs a fraction of the
    Python loop in ``_fields_generic``; anything unusual falls back to that loop.
    """
    order = ["step", "time", "run_offset", "runs", "dim", *payload]
    nums = [numbers[n] for n in order]
    if nums != sorted(nums) or len(set(nums)) != len(nums) or nums[-1] > 15:
        return None
    parts = []
    for name in order[:5]:
        tag = re.escape(bytes([numbers[name] << 3 | (1 if name == "time" else 0)]))
        parts.append(b"(?:" + tag + (b"(.{8})" if name == "time" else _VARINT_RE) + b")?")
    return re.compile(b"".join(parts), re.DOTALL)


def _read_varint(buf: Any, pos: int) -> tuple[int, int]:
    result = 0
    shift = 0
    while True:
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result, pos
        shift += 7
        if shift >= 64:
            raise _WireError("varint longer than 10 bytes")


def _varint_value(b: bytes) -> int:
    if len(b) == 2:  # steps 128..16383: most messages of a long log
        return (b[0] & 0x7F) | b[1] << 7
    result = 0
    for i, byte in enumerate(b):
        result |= (byte & 0x7F) << (7 * i)
    return result


Pieces = list[tuple[int, int]]
Fields = tuple[int, float, int, int, int, Pieces, Pieces]
"""(step, time, run_offset, runs, dim, pieces1, pieces2): a payload as (start, end) byte ranges
of the message, usually one; several when a writer split the packed field or did not pack it."""


def _join(buf: Any, pieces: Pieces) -> Any:
    if not pieces:
        return b""
    if len(pieces) == 1:  # the normal case: one packed field, no copy
        a, b = pieces[0]
        return buf[a:b]
    # A field may legally be split (several packed runs, or unpacked single doubles).
    return b"".join(bytes(buf[a:b]) for a, b in pieces)


def _fields_generic(buf: Any, keys: dict[int, int]) -> Fields:
    """Protobuf wire parse: any field order, unknown fields, split packed or unpacked doubles.

    Absent scalars are 0, as a proto3 writer omits zeros.
    """
    ints = [0, 0, 0, 0]
    t = 0.0
    p1: Pieces = []
    p2: Pieces = []
    n = len(buf)
    pos = 0
    try:
        while pos < n:
            key = buf[pos]
            pos += 1
            if key >= 0x80:
                key, pos = _read_varint(buf, pos - 1)
            action = keys.get(key)
            wt = key & 7
            if wt == 0:
                v = buf[pos]
                pos += 1
                if v >= 0x80:
                    v, pos = _read_varint(buf, pos - 1)
                if action is not None:
                    ints[action] = v
            elif wt == 2:
                ln = buf[pos]
                pos += 1
                if ln >= 0x80:
                    ln, pos = _read_varint(buf, pos - 1)
                end = pos + ln
                if end > n:
                    raise _WireError("length-delimited field runs past the end")
                if action is not None:
                    if ln % 8:
                        raise _WireError("packed double field length is not a multiple of 8")
                    (p1 if action == _A_P1 else p2).append((pos, end))
                pos = end
            elif wt == 1:
                if pos + 8 > n:
                    raise _WireError("fixed64 field runs past the end")
                if action == _A_TIME:
                    t = _F64.unpack_from(buf, pos)[0]
                elif action == _A_P1:
                    p1.append((pos, pos + 8))
                elif action == _A_P2:
                    p2.append((pos, pos + 8))
                pos += 8
            elif wt == 5:
                pos += 4
            else:
                raise _WireError(f"unsupported wire type {wt}")
        if pos != n:
            raise _WireError("message ends inside a field")
    except IndexError:
        raise _WireError("message ends inside a field") from None
    return ints[0], t, ints[1], ints[2], ints[3], p1, p2


def _payload_span(buf: Any, pos: int, n: int) -> tuple[int, int]:
    """(start, end) of the packed doubles of the length-delimited field whose tag is at ``pos``;
    (-1, -1) if malformed."""
    ln = buf[pos + 1] if pos + 1 < n else 0x80
    pos += 2
    if ln >= 0x80:
        try:
            ln, pos = _read_varint(buf, pos - 1)
        except (IndexError, _WireError):
            return -1, -1
    if pos + ln > n or ln % 8:
        return -1, -1
    return pos, pos + ln


def _fields(buf: Any, layout: _Layout) -> Fields:
    """Decode one message; canonical encodings take the regex fast path."""
    fast = layout.fast
    if fast is not None:
        m = fast.match(buf)
        pos = m.end()  # type: ignore[union-attr]  # every group is optional: always matches
        n = len(buf)
        p1: Pieces = []
        p2: Pieces = []
        # the payload fields, unrolled: tag, length, packed doubles
        if pos < n and buf[pos] == layout.p1_tag:
            a, pos = _payload_span(buf, pos, n)
            p1 = [(a, pos)]
        if 0 <= pos < n and buf[pos] == layout.p2_tag:
            a, pos = _payload_span(buf, pos, n)
            p2 = [(a, pos)]
        if pos == n:  # -1 when a payload was malformed
            gs, gt, go, gr, gd = m.groups()  # type: ignore[union-attr]
            return (
                0 if gs is None else gs[0] if len(gs) == 1 else _varint_value(gs),
                0.0 if gt is None else _F64.unpack(gt)[0],
                0 if go is None else go[0] if len(go) == 1 else _varint_value(go),
                0 if gr is None else gr[0] if len(gr) == 1 else _varint_value(gr),
                0 if gd is None else gd[0] if len(gd) == 1 else _varint_value(gd),
                p1,
                p2,
            )
    return _fields_generic(buf, layout.keys)


def _decode(buf: Any, layout: _Layout) -> Decoded:
    """Decode one message, payloads as bytes-like (views of ``buf`` where they are contiguous)."""
    step, t, off, runs, dim, q1, q2 = _fields(buf, layout)
    return step, t, off, runs, dim, _join(buf, q1), _join(buf, q2)


#: Varints of up to this many bytes are decoded in int64 columns (uint32 needs five).
_MAX_VARINT = 5


@dataclass(frozen=True)
class _Template:
    """Where the fields lie in one canonical message, so that every message of the same channel
    and length with the same tag and length bytes is decoded at once, as numpy columns.

    Equal tags, lengths and varint continuation bits at the same places make two messages of
    one length parse identically field by field; only the bytes of the values differ. The
    payload bytes are not read here: a message's payloads start at its offset + p1 / p2.
    """

    cols: np.ndarray  # positions read from every message: everything but the payload doubles
    mask: np.ndarray  # per col: 0xFF tag/length byte, 0x80 varint value byte, 0 time byte
    expect: np.ndarray  # the template's bytes & mask
    ints: tuple[tuple[int, int] | None, ...]  # step, run_offset, runs, dim: (col, bytes)
    time: int | None  # col of the time's first byte
    p1: tuple[int, int]  # (start, length) of the payloads in the message; (0, 0) if absent
    p2: tuple[int, int]

    @staticmethod
    def of(data: bytes, layout: _Layout) -> _Template | None:
        """The template of ``data``, or None if it is not canonical (decode one by one)."""
        fast = layout.fast
        if fast is None:
            return None
        n = len(data)
        m = fast.match(data)
        pos = m.end()  # type: ignore[union-attr]
        payload: list[tuple[int, int]] = []
        for tag in (layout.p1_tag, layout.p2_tag):
            if 0 <= pos < n and data[pos] == tag:
                a, pos = _payload_span(data, pos, n)
                payload.append((a, pos))
            else:
                payload.append((0, 0))
        if pos != n:
            return None
        mask = np.full(n, 0xFF, np.uint8)
        unread = np.zeros(n, bool)  # the payload doubles
        for a, b in payload:
            unread[a:b] = True
        spans = [m.span(g) for g in range(1, 6)]  # type: ignore[union-attr]
        for g, (a, b) in enumerate(spans):
            if a >= 0:
                if g != 1 and b - a > _MAX_VARINT:
                    return None
                mask[a:b] = 0 if g == 1 else 0x80
        cols = np.flatnonzero(~unread)
        where = np.full(n, -1)
        where[cols] = np.arange(len(cols))
        mask = mask[cols]
        ints = tuple(
            None if spans[g][0] < 0 else (int(where[spans[g][0]]), spans[g][1] - spans[g][0])
            for g in (0, 2, 3, 4)
        )
        time = None if spans[1][0] < 0 else int(where[spans[1][0]])
        expect = np.frombuffer(data, np.uint8)[cols] & mask
        (a1, b1), (a2, b2) = payload
        return _Template(cols, mask, expect, ints, time, (a1, b1 - a1), (a2, b2 - a2))

    def decode(
        self, u8: np.ndarray, starts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The messages at byte offsets ``starts`` of ``u8``: (ok, ints, time) with ints rows
        step, run_offset, runs, dim, p1, n1, p2, n2 (payload offsets in ``u8`` and byte
        lengths); ok is False where a message does not fit the template (decode it singly)."""
        head = u8[starts[:, None] + self.cols]
        ok = ((head & self.mask) == self.expect).all(axis=1)
        ints = np.zeros((8, len(starts)), np.int64)
        for row, spec in enumerate(self.ints):
            if spec is not None:
                c, ln = spec
                v = ints[row]
                for i in range(ln):
                    v |= (head[:, c + i] & 0x7F).astype(np.int64) << (7 * i)
        ints[4] = starts + self.p1[0]
        ints[5] = self.p1[1]
        ints[6] = starts + self.p2[0]
        ints[7] = self.p2[1]
        ok &= (ints[:4] <= _UINT32_MAX).all(axis=0)  # else decoded singly, which says why
        if self.time is None:
            time = np.zeros(len(starts))
        else:
            c = self.time
            time = np.ascontiguousarray(head[:, c : c + 8]).view("<f8")[:, 0]
        return ok, ints, time


def _layout_from_schema(schema: Schema) -> _Layout | None:
    """Layout for a protobuf schema whose message has the fusionlog fields, else None.

    Matching is by field name and type, not by schema name, so a foreign writer's schema with
    the same fields (any numbers, proto2 or proto3) is read correctly.
    """
    if schema.encoding != "protobuf":
        return None
    try:
        fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    except Exception:
        return None
    msg = None
    for fdp in fds.file:
        stack = [
            (f"{fdp.package}.{m.name}" if fdp.package else m.name, m) for m in fdp.message_type
        ]
        while stack and msg is None:
            full, m = stack.pop()
            if full == schema.name:
                msg = m
            stack.extend((f"{full}.{nm.name}", nm) for nm in m.nested_type)
        if msg is not None:
            break
    if msg is None:
        return None
    F = descriptor_pb2.FieldDescriptorProto
    fields = {f.name: f for f in msg.field}
    keys: dict[int, int] = {}
    int_types = {F.TYPE_UINT32, F.TYPE_UINT64, F.TYPE_INT32, F.TYPE_INT64}
    for action, name in enumerate(_INT_FIELDS):
        f = fields.get(name)
        if f is None or f.type not in int_types or f.label == F.LABEL_REPEATED:
            return None
        keys[f.number << 3] = action
    f = fields.get("time")
    if f is None or f.type != F.TYPE_DOUBLE or f.label == F.LABEL_REPEATED:
        return None
    keys[f.number << 3 | 1] = _A_TIME
    if "values" in fields:
        kind, payload = VALUES, ["values"]
    elif "mean" in fields and "covariance" in fields:
        kind, payload = ESTIMATE, ["mean", "covariance"]
    else:
        return None
    for action, name in zip((_A_P1, _A_P2), payload, strict=False):
        f = fields[name]
        if f.type != F.TYPE_DOUBLE or f.label != F.LABEL_REPEATED:
            return None
        keys[f.number << 3 | 2] = action  # packed
        keys[f.number << 3 | 1] = action  # unpacked, one double per tag
    numbers = {name: fields[name].number for name in ("step", "time", *_INT_FIELDS[1:], *payload)}
    fast = _fast_pattern(numbers, payload)
    tags = [numbers[name] << 3 | 2 for name in payload] + [-1]
    return _Layout(kind, keys, fast, tags[0], tags[1])


def decode_message(data: bytes, schema_name: str = SENSOR_SCHEMA) -> dict[str, Any]:
    """Decode one fusionlog message (bytes) into a dict of fields, payloads reshaped.

    For debugging and tests; the reader uses the same decoder without building dicts.
    """
    layout = _layout_for_name(schema_name)
    step, t, off, runs, dim, p1, p2 = _decode(data, layout)
    out: dict[str, Any] = {"step": step, "time": t, "run_offset": off, "runs": runs, "dim": dim}
    a1 = np.frombuffer(p1, dtype="<f8")
    if layout.kind == VALUES:
        out["values"] = a1.reshape(runs, dim)
    else:
        a2 = np.frombuffer(p2, dtype="<f8")
        out["mean"] = a1.reshape(runs, dim)
        out["covariance"] = a2.reshape((dim, dim) if a2.size == dim * dim else (runs, dim, dim))
    return out


@lru_cache(maxsize=2)
def _layout_for_name(schema_name: str) -> _Layout:
    schema = Schema(id=0, data=file_descriptor_set(), encoding="protobuf", name=schema_name)
    layout = _layout_from_schema(schema)
    if layout is None:
        raise ValueError(f"unknown fusionlog schema {schema_name!r}")
    return layout


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------

_COMPRESSION = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None}


class McapWriter:
    """Write a fusionlog MCAP file atomically (temp file in the target folder, renamed on success).

    The MCAP records are written by the Foxglove SDK's MCAP writer (Rust, ``foxglove-sdk``): the
    pure-Python ``mcap.writer`` spends ~7 µs per message, which capped a one-run log near 10^5
    messages/s. Its header names that library (``foxglove-sdk-python/... mcap-rust/...``);
    which fusionlog wrote the file is in the ``fusionlog.provenance`` metadata.

    Chunks are uncompressed by default: random float64 payloads shrink by only ~7 % under zstd,
    which cost about a third of the estimate stage and most of the per-message write rate; the
    chunk CRCs (validated on reading) still catch corruption.

    Use as a context manager. Messages must come in the documented order: for each block of runs
    (contiguous from run 0), for each step, for each topic, one message; the writer checks this
    cheaply so a bug in a stage fails here rather than when the file is read.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        force: bool = False,
        compression: str = "none",
        chunk_size: int = 1024 * 1024,
    ) -> None:
        self.path = Path(path)
        self.force = force
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}")
        self._compression = _COMPRESSION[compression]
        self._chunk_size = chunk_size
        # Checked before anything is created so a refused run leaves no trace.
        if self.path.is_dir():
            raise FusionlogError(f"{self.path}: is a directory, not an output file")
        if self.path.exists() and not force:
            raise FusionlogError(f"{self.path}: exists; use --force to overwrite")
        self._tmp: Path | None = None
        self._ctx: foxglove.Context | None = None
        self._writer: MCAPWriter | None = None
        self._schemas: dict[str, foxglove.Schema] = {}
        self._topic_states: dict[str, _TopicState] = {}
        self._messages = 0
        self._block_offset, self._block_runs = -1, 0  # block of runs being written
        self._seen: set[tuple[int, int]] = set()  # (channel, step) in the current block
        self._hstep: int = -1  # step and time whose encoded fields are in _head
        self._htime: float = math.nan
        self._head = b""
        self._t_ns = 0

    def __enter__(self) -> McapWriter:
        parent = self.path.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise FusionlogError(f"{self.path}: cannot create folder {parent}: {e}") from e
        # The temp name is claimed with O_EXCL (0o666, so the final file gets the umask's mode);
        # the SDK then writes into that file, which is ours to overwrite.
        for _ in range(100):
            tmp = parent / f".{self.path.name}.{secrets.token_hex(4)}.tmp"
            try:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                break
            except FileExistsError:
                continue
            except OSError as e:
                raise FusionlogError(f"{self.path}: cannot write in {parent}: {e}") from e
        else:  # pragma: no cover - 100 collisions of 32 random bits
            raise FusionlogError(f"{self.path}: cannot create a temporary file in {parent}")
        self._tmp = tmp
        try:
            # A context of its own per file: channels and sinks do not leak between files.
            self._ctx = foxglove.Context()
            options = MCAPWriteOptions(
                compression=self._compression,
                chunk_size=self._chunk_size,
                profile="",
                compression_threads=0,  # same bytes whatever the machine
            )
            self._writer = foxglove.open_mcap(
                tmp, allow_overwrite=True, context=self._ctx, writer_options=options
            )
        except BaseException:
            self._abort()
            raise
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self._abort()
            return
        try:
            assert self._writer is not None and self._tmp is not None
            writer, self._writer = self._writer, None  # further writes fail loudly
            try:
                writer.close()
            except RuntimeError as e:  # the SDK reports a failed write (disk full) here
                raise FusionlogError(f"{self.path}: cannot write: {_one_line(e)}") from None
            self._check_written(self._tmp)
            with open(self._tmp, "rb") as f:
                os.fsync(f.fileno())
            if not self.force and self.path.exists():  # appeared while we were writing
                raise FusionlogError(f"{self.path}: exists; use --force to overwrite")
            os.replace(self._tmp, self.path)
            self._tmp = None
        except BaseException:  # includes KeyboardInterrupt during close
            self._abort()
            raise

    def _check_written(self, tmp: Path) -> None:
        """The file's summary counts every message handed over: the SDK only logs (does not
        raise) a message it failed to record, so a silent loss would otherwise go unnoticed."""
        try:
            with open(tmp, "rb") as f:
                summary = SeekingReader(f).get_summary()
            count = summary.statistics.message_count if summary and summary.statistics else -1
        except (McapError, OSError, ValueError) as e:
            raise FusionlogError(f"{self.path}: written file does not read back: {e}") from None
        if count != self._messages:
            raise FusionlogError(
                f"{self.path}: wrote {self._messages} messages, the file holds {count}"
            )

    def _abort(self) -> None:
        """Close and delete the temp file; never raises, so the original error propagates."""
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:
                pass
            self._writer = None
        if self._tmp is not None:
            try:
                self._tmp.unlink()
            except OSError:
                pass
            self._tmp = None

    def _live_writer(self) -> MCAPWriter:
        if self._writer is None:
            raise RuntimeError("McapWriter is not open; use it as a context manager")
        return self._writer

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (e.g. ``fusionlog.scenario``, ``fusionlog.provenance``)."""
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise TypeError(f"metadata {name!r} must map str to str")
        self._live_writer().write_metadata(name, dict(data))

    def _new_topic(self, topic: str, kind: str, dim: int) -> _TopicState:
        st = self._topic_states.get(topic)
        if st is not None:
            if st.kind != kind:
                raise ValueError(f"topic {topic!r} was written as {st.kind}, not {kind}")
            raise ValueError(f"topic {topic!r} has dim {st.dim}, got a message with dim {dim}")
        if not topic or not isinstance(topic, str):
            raise ValueError(f"bad topic {topic!r}")
        self._live_writer()
        assert self._ctx is not None
        schema_name = SENSOR_SCHEMA if kind == VALUES else ESTIMATE_SCHEMA
        schema = self._schemas.get(schema_name)
        if schema is None:
            schema = foxglove.Schema(
                name=schema_name, encoding="protobuf", data=file_descriptor_set()
            )
            self._schemas[schema_name] = schema
        channel = foxglove.Channel(
            topic, schema=schema, message_encoding="protobuf", context=self._ctx
        )
        st = _TopicState(len(self._topic_states), channel.base.log, kind, dim)
        self._topic_states[topic] = st
        return st

    def _new_block(self, topic: str, run_offset: int, runs: int) -> None:
        run_offset = operator.index(run_offset)
        if run_offset == self._block_offset:
            raise ValueError(
                f"{topic}: block at run {run_offset} has {self._block_runs} runs, got {runs}"
            )
        expected = 0 if self._block_offset < 0 else self._block_offset + self._block_runs
        if run_offset != expected:
            raise ValueError(
                f"{topic}: block of runs starts at {run_offset}, expected {expected} "
                "(blocks of runs must be written in order, contiguously from run 0)"
            )
        if run_offset + runs - 1 > _UINT32_MAX:
            raise ValueError("run indices must fit in uint32")
        self._block_offset, self._block_runs = run_offset, runs
        self._seen.clear()

    def _set_head(self, step: int, time: float) -> None:
        """Encode the step and time fields once per step: every topic of the step shares them."""
        step = operator.index(step)
        time = float(time) + 0.0  # + 0.0 turns -0.0 into 0.0, which proto3 omits
        if not 0 <= step <= _UINT32_MAX:
            raise ValueError(f"step must fit in uint32, got {step}")
        if not (time >= 0.0 and math.isfinite(time)):  # log_time is an unsigned ns count
            raise ValueError(f"time must be finite and >= 0, got {time}")
        t = _F64.pack(time)
        head = (b"\x08" + _varint(step)) if step else b""
        if time:
            head += b"\x11" + t
        self._hstep, self._htime = step, time
        self._head, self._t_ns = head, round(time * 1e9)

    def _write(
        self,
        topic: str,
        kind: str,
        step: int,
        time: float,
        run_offset: int,
        runs: int,
        dim: int,
        p1: bytes,
        p2: bytes,
    ) -> None:
        # The hot path: a few dict/set operations and one bytes join per message; everything
        # that only changes per step, per topic or per block is cached.
        if self._writer is None:
            raise RuntimeError("McapWriter is not open; use it as a context manager")
        st = self._topic_states.get(topic)
        if st is None or st.kind != kind or st.dim != dim:
            st = self._new_topic(topic, kind, dim)
        if run_offset != self._block_offset or runs != self._block_runs:
            self._new_block(topic, run_offset, runs)
        key = (st.cid, step)
        if key in self._seen:
            raise ValueError(f"{topic}: step {step} written twice for runs from {run_offset}")
        self._seen.add(key)
        if step != self._hstep or time != self._htime:
            self._set_head(step, time)
        if st.mid_key != (run_offset, runs, len(p2)):
            st.set_mid(run_offset, runs, len(p2))
        st.log(b"".join((self._head, st.mid, p1, st.mid2, p2)), self._t_ns)
        self._messages += 1

    def write_values(
        self, topic: str, step: int, time: float, run_offset: int, values: np.ndarray
    ) -> None:
        """Write one ``fusionlog.Block``: ``values`` (runs, dim) at ``step`` for a block of runs."""
        if type(values) is not np.ndarray or values.dtype != _F8:
            values = np.asarray(values, dtype=_F8)
        shape = values.shape
        if len(shape) != 2 or shape[0] < 1 or shape[1] < 1:
            raise ValueError(f"values must have shape (runs >= 1, dim >= 1), got {shape}")
        # tobytes() is C order whatever the strides, so no ascontiguousarray copy is needed.
        self._write(
            topic, VALUES, step, time, run_offset, shape[0], shape[1], values.tobytes(), b""
        )

    def write_estimate(
        self,
        topic: str,
        step: int,
        time: float,
        run_offset: int,
        mean: np.ndarray,
        cov: np.ndarray,
    ) -> None:
        """Write one ``fusionlog.EstimateBlock``: mean (runs, n), cov (n, n) or (runs, n, n)."""
        m = mean if type(mean) is np.ndarray and mean.dtype == _F8 else np.asarray(mean, _F8)
        c = cov if type(cov) is np.ndarray and cov.dtype == _F8 else np.asarray(cov, _F8)
        if m.ndim != 2 or m.shape[0] < 1 or m.shape[1] < 1:
            raise ValueError(f"mean must have shape (runs >= 1, n >= 1), got {m.shape}")
        runs, n = m.shape
        if c.shape != (n, n) and c.shape != (runs, n, n):
            raise ValueError(f"cov must have shape ({n}, {n}) or ({runs}, {n}, {n}), got {c.shape}")
        self._write(topic, ESTIMATE, step, time, run_offset, runs, n, m.tobytes(), c.tobytes())


class _TopicState:
    """Per-topic writer state: channel number and its log function (payload, log_time in ns;
    the SDK sets publish_time = log_time), kind, dim and the cached run_offset/runs/dim fields."""

    __slots__ = ("cid", "log", "kind", "dim", "mid_key", "mid", "mid2")

    def __init__(self, cid: int, log: Any, kind: str, dim: int) -> None:
        self.cid, self.log, self.kind, self.dim = cid, log, kind, dim
        self.mid_key: tuple[int, int, int] | None = None
        self.mid = self.mid2 = b""

    def set_mid(self, run_offset: int, runs: int, cov_len: int) -> None:
        """Encode run_offset, runs, dim and the payload tags/lengths (fixed within a block)."""
        mid = b"\x18" + _varint(run_offset) if run_offset else b""
        mid += b"\x20" + _varint(runs) + b"\x28" + _varint(self.dim)
        mid += b"\x32" + _varint(runs * self.dim * 8)
        self.mid = mid
        self.mid2 = b"\x3a" + _varint(cov_len) if cov_len else b""
        self.mid_key = (run_offset, runs, cov_len)


# --------------------------------------------------------------------------------------------
# Reader
# --------------------------------------------------------------------------------------------


def _one_line(e: BaseException) -> str:
    """Exception text for a one-line user message (library messages may contain newlines)."""
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _recover_hint(path: Path) -> str:
    return f"`fusionlog inspect --recover {path}` shows what is still readable"


def _open_error(path: Path, e: OSError) -> FusionlogError:
    if isinstance(e, FileNotFoundError):
        return FusionlogError(f"{path}: no such file")
    if isinstance(e, IsADirectoryError):
        return FusionlogError(f"{path}: is a directory, not an MCAP file")
    if isinstance(e, PermissionError):
        return FusionlogError(f"{path}: permission denied")
    return FusionlogError(f"{path}: cannot read: {e.strerror or e}")


@dataclass
class _TopicInfo:
    channel_ids: list[int]
    schema: str
    message_encoding: str
    layout: _Layout | None
    count: int = 0


@dataclass
class _Structure:
    """What the first block of runs and the last messages say about the whole file."""

    times: np.ndarray
    dims: dict[str, int]
    runs: int


@dataclass
class _Est:
    """Assembly buffers of one estimate topic in one output block."""

    mean: np.ndarray
    shared: np.ndarray | None = None  # (S, n, n) while every file block had one shared cov
    shared_raw: bytes | None = None  # its bytes, to compare with the next file block's
    per_run: np.ndarray | None = None  # (runs, S, n, n) once covariances differ between runs

    def to_per_run(self, runs: int) -> None:
        """Switch to per-run covariances; rows filled so far had the shared one."""
        m = self.mean.shape
        self.per_run = np.empty((runs, m[1], m[2], m[2]))
        if self.shared is not None:
            self.per_run[:] = self.shared


@dataclass
class _OutBlock:
    lo: int
    hi: int
    arrays: dict[int, Any] = field(default_factory=dict)  # topic index -> ndarray | _Est


#: Messages shorter than this are decoded a group at a time (``_Template``), longer ones singly:
#: their bytes dominate, and a template would have to be checked against every payload length.
_SMALL = 4096
#: Messages (at most) and bytes (about) per table when a file without index is read linearly.
_LINEAR_BATCH = 8192
_LINEAR_BYTES = 1 << 20
#: Payloads of more doubles than this are copied one message at a time (no index arrays).
_GATHER_LOOP = 1024


@dataclass
class _Table:
    """The wanted messages of one chunk, decoded into columns, in file order.

    The payloads stay in ``raw`` (the messages' bytes joined, then any payload that had to be
    reassembled from pieces): p1/p2 are their byte offsets in it, n1/n2 their byte lengths.
    """

    raw: bytes
    cid: np.ndarray
    step: np.ndarray
    off: np.ndarray
    runs: np.ndarray
    dim: np.ndarray
    time: np.ndarray
    p1: np.ndarray
    n1: np.ndarray
    p2: np.ndarray
    n2: np.ndarray

    def __len__(self) -> int:
        return len(self.cid)


def _gather(raw: bytes, starts: np.ndarray, nvals: int) -> np.ndarray:
    """(len(starts), nvals) little-endian doubles read from ``raw`` at byte offsets ``starts``.

    The offsets are rarely multiples of 8; numpy reads unaligned arrays, so ``raw`` is viewed
    as doubles once per residue mod 8 and whole doubles are gathered (an index per double,
    not per byte).
    """
    count = len(starts)
    out = np.empty((count, nvals), _F8)
    if not count or not nvals:
        return out
    if nvals > _GATHER_LOOP:
        for i, s in enumerate(starts.tolist()):
            out[i] = np.frombuffer(raw, _F8, nvals, s)
        return out
    res = starts & 7
    cols = np.arange(nvals)
    for j in np.flatnonzero(np.bincount(res, minlength=8)).tolist():
        view = np.frombuffer(raw, _F8, (len(raw) - j) // 8, j)
        sel = res == j
        at = (starts[sel] - j) >> 3
        out[sel] = view[at[:, None] + cols]
    return out


@dataclass(frozen=True)
class _Window:
    """Runs [a, b) of the file block of runs [o, o + r); check: validate its messages (first
    reading) or trust them (a window read again)."""

    o: int
    r: int
    a: int
    b: int
    check: bool


#: Where reading stands: a (chunk ordinal, table) and a row of it; no table at the end.
_Cursor = tuple[tuple[int, "_Table"] | None, int]


class _Assembly:
    """Copies decoded tables into output blocks of runs, for ``McapFile.iter_run_blocks``.

    Holds at most two output blocks (``pending``) and, for the file block being read, which
    steps each topic had and the shared covariances met so far (reset by ``end_block``).
    """

    def __init__(
        self,
        path: Path,
        names: list[str],
        dims: list[int],
        kinds: list[str],
        topic_index: np.ndarray,
        steps: int,
        total: int,
        block_runs: int,
    ) -> None:
        self.path, self.names, self.dims, self.kinds = path, names, dims, kinds
        self.topic_index = topic_index  # channel id -> index into names
        self.S, self.total, self.block_runs = steps, total, block_runs
        self.pending: list[_OutBlock] = []
        self.next_lo = 0
        self.seen = [np.zeros(steps, bool) for _ in names]
        self.shared = [
            np.zeros((steps, d, d)) if k == ESTIMATE else None
            for k, d in zip(kinds, dims, strict=True)
        ]
        self.has_shared = [np.zeros(steps, bool) for _ in names]
        self.any_per_run = [False for _ in names]

    def bad(self, msg: str) -> FusionlogError:
        return FusionlogError(f"{self.path}: {msg} (fusionlog block order violated)")

    def add_blocks(self, upto: int) -> int:
        """Open output blocks (at most two) towards run ``upto``; return the window end."""
        pending = self.pending
        while (
            len(pending) < 2
            and (not pending or pending[-1].hi < upto)
            and self.next_lo < self.total
        ):
            lo, hi = self.next_lo, min(self.next_lo + self.block_runs, self.total)
            blk = _OutBlock(lo, hi)
            for ti, d in enumerate(self.dims):
                shape = (hi - lo, self.S, d)
                blk.arrays[ti] = (
                    np.empty(shape) if self.kinds[ti] == VALUES else _Est(np.empty(shape))
                )
            pending.append(blk)
            self.next_lo = hi
        return min(upto, pending[-1].hi)

    def overlaps(self, w: _Window) -> Iterator[tuple[_OutBlock, slice, slice]]:
        """Output blocks meeting the window's runs: (block, its rows, rows of the window)."""
        for blk in self.pending:
            x, y = max(w.a, blk.lo), min(w.b, blk.hi)
            if x < y:
                yield blk, slice(x - blk.lo, y - blk.lo), slice(x - w.a, y - w.a)

    def read_block(self, tables: Iterator[tuple[int, _Table]], cur: _Cursor, w: _Window) -> _Cursor:
        """Copy the window of the file block that starts at ``cur`` into the output blocks;
        return where the next file block starts."""
        item, i = cur
        while item is not None:
            tab = item[1]
            other = np.flatnonzero(tab.off[i:] != w.o)
            j = i + int(other[0]) if len(other) else len(tab)
            self.add_rows(tab, i, j, w)
            if j < len(tab):
                i = j
                break
            item, i = next(tables, None), 0
        self.end_block(w)
        return item, i

    def check_rows(self, tab: _Table, sel: np.ndarray, ti: int, w: _Window) -> None:
        """The messages ``sel`` of topic ``ti`` fit the file block at run ``w.o``."""
        name, d, o, r = self.names[ti], self.dims[ti], w.o, w.r
        steps = tab.step[sel]
        wrong = np.flatnonzero(tab.runs[sel] != r)
        if len(wrong):
            i = sel[wrong[0]]
            raise self.bad(
                f"{name}: messages of the block at run {o} disagree on runs (step "
                f"{tab.step[i]} has runs={tab.runs[i]}, the block's first message {r})"
            )
        if steps.max() >= self.S:
            raise self.bad(f"{name}: step {steps.max()} beyond the file's {self.S} steps")
        # twice: in an earlier table of this block, or twice in this one
        twice = steps[self.seen[ti][steps]]
        if not len(twice):
            ordered = np.sort(steps)
            twice = ordered[1:][ordered[1:] == ordered[:-1]]
        if len(twice):
            raise self.bad(f"{name}: step {twice[0]} appears twice for runs from {o}")
        wrong = np.flatnonzero((tab.dim[sel] != d) | (tab.n1[sel] != r * d * 8))
        if len(wrong):
            i = sel[wrong[0]]
            raise FusionlogError(
                f"{self.path}: {name}: step {tab.step[i]} runs from {o}: payload of "
                f"{tab.n1[i] // 8} doubles does not match runs={r}, dim={tab.dim[i]} "
                f"(topic dim {d})"
            )
        if self.kinds[ti] == ESTIMATE:
            n2 = tab.n2[sel]
            wrong = np.flatnonzero((n2 != d * d * 8) & (n2 != r * d * d * 8))
            if len(wrong):
                i = sel[wrong[0]]
                raise FusionlogError(
                    f"{self.path}: {name}: step {tab.step[i]} runs from {o}: covariance of "
                    f"{tab.n2[i] // 8} doubles is neither n*n nor runs*n*n"
                )

    def add_rows(self, tab: _Table, i: int, j: int, w: _Window) -> None:
        """Copy the window's runs of rows [i, j) of ``tab`` into the output blocks."""
        of_topic = self.topic_index[tab.cid[i:j]]
        rows, skip = w.b - w.a, w.a - w.o  # a window's rows of a message: from row a - o on
        for ti, d in enumerate(self.dims):
            sel = i + np.flatnonzero(of_topic == ti)
            if not len(sel):
                continue
            if w.check:
                self.check_rows(tab, sel, ti, w)
            steps = tab.step[sel]
            self.seen[ti][steps] = True
            vals = _gather(tab.raw, tab.p1[sel] + skip * d * 8, rows * d)
            vals = vals.reshape(len(sel), rows, d)
            estimate = self.kinds[ti] == ESTIMATE
            for blk, dst, src in self.overlaps(w):
                out = blk.arrays[ti].mean if estimate else blk.arrays[ti]
                out[dst, steps] = vals[:, src].swapaxes(0, 1)
            if not estimate:
                continue
            # A covariance of n*n values is shared by the message's runs (for a one-run
            # message both readings agree); shared ones are placed when the block ends.
            sh = tab.n2[sel] == d * d * 8
            if sh.any():
                k = steps[sh]
                self.shared[ti][k] = _gather(tab.raw, tab.p2[sel[sh]], d * d).reshape(-1, d, d)  # type: ignore[index]
                self.has_shared[ti][k] = True
            if not sh.all():
                self.any_per_run[ti] = True
                pr = sel[~sh]
                covs = _gather(tab.raw, tab.p2[pr] + skip * d * d * 8, rows * d * d)
                covs = covs.reshape(len(pr), rows, d, d)
                for blk, dst, src in self.overlaps(w):
                    est: _Est = blk.arrays[ti]
                    if est.per_run is None:
                        est.to_per_run(blk.hi - blk.lo)
                    est.per_run[dst, steps[~sh]] = covs[:, src].swapaxes(0, 1)  # type: ignore[index]

    def end_block(self, w: _Window) -> None:
        """Every step of every topic came; place the block's shared covariances; reset."""
        for ti, name in enumerate(self.names):
            seen = self.seen[ti]
            if w.check and not seen.all():
                raise self.bad(
                    f"{name}: {seen.sum()} of {self.S} steps for the block of runs at run {w.o}"
                )
            seen[:] = False
            cov, some = self.shared[ti], self.has_shared[ti]
            if cov is None:
                continue
            for blk, dst, _ in self.overlaps(w):
                est: _Est = blk.arrays[ti]
                if self.any_per_run[ti]:  # est.per_run exists: add the steps that were shared
                    est.per_run[dst, some] = cov[some]  # type: ignore[index]
                    continue
                if est.per_run is None:
                    raw = cov.tobytes()
                    if est.shared_raw is None:
                        # A copy per output block: writable, and not aliased between blocks
                        # that the caller may modify.
                        est.shared_raw, est.shared = raw, cov.copy()
                        continue
                    if est.shared_raw == raw:
                        continue
                    # Shared within each file block but different between them.
                    est.to_per_run(blk.hi - blk.lo)
                est.per_run[dst] = cov  # type: ignore[index]
            some[:] = False
            self.any_per_run[ti] = False

    def finished(self, upto: int) -> Iterator[tuple[int, int, dict[str, Any]]]:
        """Hand over the output blocks that end at or before run ``upto``."""
        while self.pending and self.pending[0].hi <= upto:
            blk = self.pending.pop(0)
            out: dict[str, Any] = {}
            for ti, t in enumerate(self.names):
                arr = blk.arrays[ti]
                if self.kinds[ti] == VALUES:
                    out[t] = arr
                else:
                    out[t] = (arr.mean, arr.shared if arr.per_run is None else arr.per_run)
            yield blk.lo, blk.hi - blk.lo, out


class McapFile:
    """A fusionlog MCAP file opened for reading; opening validates the container and schemas.

    Holds no open file handle: every read opens its own, so instances are cheap and need no
    closing.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._chunks: list[tuple[ChunkIndex, set[int] | None]] = []
        self._linear = False
        self._structure: _Structure | None = None
        self.metadata: dict[str, dict[str, str]] = {}
        self.library = ""
        try:
            with open(self.path, "rb") as f:
                self._open(f)
        except OSError as e:
            raise _open_error(self.path, e) from e
        self.topics: dict[str, int] = {t: info.count for t, info in self._topics.items()}

    # -- opening -------------------------------------------------------------------------------

    def _open(self, f: BinaryIO) -> None:
        path = self.path
        size = os.fstat(f.fileno()).st_size
        head = f.read(len(_MAGIC))
        if head != _MAGIC:
            what = "empty file" if size == 0 else "does not start with the MCAP magic bytes"
            raise FusionlogError(f"{path}: not an MCAP file ({what})")
        f.seek(max(0, size - len(_MAGIC)))
        if size < 2 * len(_MAGIC) or f.read(len(_MAGIC)) != _MAGIC:
            raise FusionlogError(
                f"{path}: truncated MCAP file (it ends before its footer; the writer was "
                f"interrupted or the copy is incomplete); {_recover_hint(path)}"
            )
        try:
            f.seek(0)
            reader = SeekingReader(f)
            self.library = reader.get_header().library
            summary = reader.get_summary()
            if summary is not None:
                self.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except (McapError, struct.error, EOFError, ValueError, UnicodeDecodeError) as e:
            raise FusionlogError(
                f"{path}: corrupt MCAP file (footer or summary unreadable: "
                f"{_one_line(e)}); {_recover_hint(path)}"
            ) from e

        stats = summary.statistics if summary is not None else None
        complete = (
            summary is not None
            and stats is not None
            and all(cid in summary.channels for cid in stats.channel_message_counts)
            and all(
                c.schema_id in summary.schemas for c in summary.channels.values() if c.schema_id
            )
            and (stats.message_count == 0 or len(summary.chunk_indexes) > 0)
        )
        if complete:
            assert summary is not None and stats is not None
            schemas, channels = summary.schemas, summary.channels
            counts = dict(stats.channel_message_counts)
            for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
                ids = set(ci.message_index_offsets) if ci.message_index_offsets else None
                self._chunks.append((ci, ids))
        else:
            # No usable index (written without summary/statistics/chunks): one linear scan.
            self._linear = True
            schemas, channels, counts = self._scan_linear(f)

        self._topics: dict[str, _TopicInfo] = {}
        layouts: dict[int, _Layout | None] = {}
        for cid in sorted(channels):
            ch = channels[cid]
            schema = schemas.get(ch.schema_id)
            layout = None
            if schema is not None and ch.message_encoding == "protobuf":
                if schema.id not in layouts:
                    layouts[schema.id] = _layout_from_schema(schema)
                layout = layouts[schema.id]
                if layout is None and schema.name in (SENSOR_SCHEMA, ESTIMATE_SCHEMA):
                    raise FusionlogError(
                        f"{path}: topic {ch.topic} claims schema {schema.name} but its "
                        "descriptor lacks the fusionlog fields"
                    )
            name = schema.name if schema is not None else ""
            info = self._topics.get(ch.topic)
            if info is None:
                info = _TopicInfo([], name, ch.message_encoding, layout)
                self._topics[ch.topic] = info
            elif (info.layout and info.layout.kind) != (layout and layout.kind):
                raise FusionlogError(
                    f"{path}: topic {ch.topic} has channels with different schemas "
                    f"({info.schema}, {name})"
                )
            info.channel_ids.append(cid)
            info.count += counts.get(cid, 0)
        self._layouts: dict[int, _Layout] = {}
        for info in self._topics.values():
            if info.layout is not None:
                for cid in info.channel_ids:
                    self._layouts[cid] = info.layout

    def _scan_linear(
        self, f: BinaryIO
    ) -> tuple[dict[int, Schema], dict[int, Channel], dict[int, int]]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        counts: dict[int, int] = {}
        f.seek(0)
        try:
            for rec in StreamReader(f).records:
                if isinstance(rec, Message):
                    counts[rec.channel_id] = counts.get(rec.channel_id, 0) + 1
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Metadata):
                    self.metadata[rec.name] = dict(rec.metadata)
        except (McapError, struct.error, EOFError, ValueError) as e:
            raise FusionlogError(
                f"{self.path}: corrupt MCAP file ({_one_line(e)}); {_recover_hint(self.path)}"
            ) from e
        unknown = set(counts) - set(channels)
        if unknown:
            raise FusionlogError(f"{self.path}: messages on undeclared channels {sorted(unknown)}")
        return schemas, channels, counts

    # -- decoded chunks ------------------------------------------------------------------------

    def _read_chunk(
        self, f: BinaryIO, ci: ChunkIndex, only: set[int] | None = None
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
            data = BytesIO(stream.read(size))
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
            raise FusionlogError(
                f"{self.path}: corrupt MCAP chunk at byte {ci.chunk_start_offset} "
                f"({_one_line(e)}); {_recover_hint(self.path)}"
            ) from e

    def _linear_batches(self, f: BinaryIO, cids: set[int]) -> Iterator[list[Message]]:
        """The messages of ``cids`` in a file without index, read from its start in batches
        (at most _LINEAR_BATCH messages or _LINEAR_BYTES bytes: memory as with chunks)."""
        f.seek(0)
        records = iter(StreamReader(f).records)
        batch: list[Message] = []
        size = 0
        while True:
            try:
                rec = next(records, None)
            except (McapError, struct.error, EOFError, ValueError) as e:
                raise FusionlogError(
                    f"{self.path}: corrupt MCAP file ({_one_line(e)}); {_recover_hint(self.path)}"
                ) from e
            if isinstance(rec, Message) and rec.channel_id in cids:
                batch.append(rec)
                size += len(rec.data)
            if rec is None or len(batch) == _LINEAR_BATCH or size >= _LINEAR_BYTES:
                if batch:
                    yield batch
                if rec is None:
                    return
                batch, size = [], 0

    def _tables(self, cids: set[int], start: int = 0) -> Iterator[tuple[int, _Table]]:
        """(ordinal, table) of every chunk from the ``start``-th that has messages of ``cids``.

        Ordinals count chunks (batches of messages in a file without index), so a block of runs
        can be read again from where it started without keeping its bytes.
        """
        with open(self.path, "rb") as f:
            if self._linear:
                for bi, batch in enumerate(self._linear_batches(f, cids)):
                    tab = self._table(batch, cids) if bi >= start else None
                    if tab is not None:
                        yield bi, tab
                return
            # Few of the file's messages wanted (evaluate reads /truth only, which every chunk
            # interleaves with the sensors): take them through the chunks' message indexes.
            wanted = sum(i.count for i in self._topics.values() if set(i.channel_ids) & cids)
            total = sum(i.count for i in self._topics.values())
            sparse = 2 * wanted <= total
            for ci in range(start, len(self._chunks)):
                index, ids = self._chunks[ci]
                if ids is not None and not ids & cids:
                    continue
                only = cids & ids if sparse and ids is not None else None
                tab = self._table(self._read_chunk(f, index, only), cids)
                if tab is not None:
                    yield ci, tab

    def _table(self, msgs: list[Message], cids: set[int]) -> _Table | None:
        """Decode the messages of ``cids`` among ``msgs`` into columns.

        Messages shorter than _SMALL are grouped by channel and length and each group decoded
        at once against the template of its first message (a fusionlog writer's messages of
        one topic differ only in their values, except where the step's varint grows); the rest,
        and any message that does not fit its group's template, one by one. The per-message
        Python work left is three list comprehensions and a map.
        """
        keep = [m for m in msgs if m.channel_id in cids]
        n = len(keep)
        if not n:
            return None
        datas = [m.data for m in keep]
        cid = np.fromiter([m.channel_id for m in keep], np.int64, n)
        lens = np.fromiter(map(len, datas), np.int64, n)
        starts = np.zeros(n, np.int64)
        np.cumsum(lens[:-1], out=starts[1:])
        raw = b"".join(datas)
        del keep, datas
        u8 = np.frombuffer(raw, np.uint8)
        # step, run_offset, runs, dim, p1, n1, p2, n2 (payload offsets in raw and byte lengths)
        cols = np.zeros((8, n), np.int64)
        time = np.zeros(n)
        done = np.zeros(n, bool)
        small = np.flatnonzero(lens < _SMALL)
        if len(small):
            key = cid[small] << 32 | lens[small]
            order = np.argsort(key, kind="stable")
            bounds = np.flatnonzero(np.diff(key[order])) + 1
            for g in np.split(small[order], bounds):
                s0 = int(starts[g[0]])
                tpl = _Template.of(raw[s0 : s0 + int(lens[g[0]])], self._layouts[int(cid[g[0]])])
                if tpl is None:
                    continue
                ok, ints, t = tpl.decode(u8, starts[g])
                if not ok.all():
                    g, ints, t = g[ok], ints[:, ok], t[ok]
                cols[:, g] = ints
                time[g] = t
                done[g] = True
        rest = np.flatnonzero(~done)
        if len(rest):
            raw = self._decode_rows(raw, rest, cid, starts, lens, cols, time)
        step, off, runs, dim, p1, n1, p2, n2 = cols
        return _Table(raw, cid, step, off, runs, dim, time, p1, n1, p2, n2)

    def _decode_rows(
        self,
        raw: bytes,
        rows: np.ndarray,
        cid: np.ndarray,
        starts: np.ndarray,
        lens: np.ndarray,
        cols: np.ndarray,
        time: np.ndarray,
    ) -> bytes:
        """Decode ``rows`` one by one into ``cols``/``time``; return ``raw`` with any payload
        that was split into pieces appended whole (payloads must be contiguous in the table)."""
        mv = memoryview(raw)
        extra: list[bytes] = []
        end = len(raw)
        for i in rows.tolist():
            s, c = int(starts[i]), int(cid[i])
            try:
                fields = _fields(mv[s : s + int(lens[i])], self._layouts[c])
            except _WireError as e:
                topic = self._topic_of()[c]
                raise FusionlogError(f"{self.path}: bad protobuf message on {topic}: {e}") from e
            step, t, off, runs, dim, q1, q2 = fields
            if max(step, off, runs, dim) > _UINT32_MAX:
                topic = self._topic_of()[c]
                raise FusionlogError(
                    f"{self.path}: bad protobuf message on {topic}: step {step}, run_offset "
                    f"{off}, runs {runs}, dim {dim}: each must fit in 32 bits"
                )
            cols[:4, i] = step, off, runs, dim
            time[i] = t
            for j, q in ((4, q1), (6, q2)):
                if len(q) == 1:
                    cols[j, i], cols[j + 1, i] = s + q[0][0], q[0][1] - q[0][0]
                elif q:
                    piece = b"".join(mv[s + a : s + b] for a, b in q)
                    extra.append(piece)
                    cols[j, i], cols[j + 1, i] = end, len(piece)
                    end += len(piece)
        mv.release()
        return b"".join([raw, *extra]) if extra else raw

    # -- structure -----------------------------------------------------------------------------

    def _topic_of(self) -> dict[int, str]:
        return {cid: t for t, i in self._topics.items() for cid in i.channel_ids}

    def _get_structure(self) -> _Structure:
        """Steps, times and dims from the first block of runs; total runs from the last one."""
        if self._structure is not None:
            return self._structure
        cids = set(self._layouts)
        topic_of = self._topic_of()
        recorded = self._recorded_structure(cids, topic_of)
        if recorded is not None:
            self._structure = recorded
            return recorded
        # Reduced chunk by chunk to each step's first time and each topic's first dim, since a
        # one-run log's first block is the whole file: memory grows with the steps only.
        step_parts: list[np.ndarray] = []
        time_parts: list[np.ndarray] = []
        dims: dict[str, int] = {}
        first: int | None = None
        for _, tab in self._tables(cids):
            if first is None:
                first = int(tab.off[0])
            other = np.flatnonzero(tab.off != first)
            j = int(other[0]) if len(other) else len(tab)
            steps, at = np.unique(tab.step[:j], return_index=True)
            step_parts.append(steps)
            time_parts.append(tab.time[at])
            _, at = np.unique(tab.cid[:j], return_index=True)
            for i in sorted(at.tolist()):
                dims.setdefault(topic_of[int(tab.cid[i])], int(tab.dim[i]))
            if j < len(tab):
                break
        times = np.zeros(0)
        if step_parts:
            steps, at = np.unique(np.concatenate(step_parts), return_index=True)
            if steps[-1] != len(steps) - 1:
                raise FusionlogError(
                    f"{self.path}: the steps of the first block of runs are not 0..K "
                    f"(found {len(steps)} distinct steps, largest {steps[-1]})"
                )
            times = np.concatenate(time_parts)[at]
        if first not in (None, 0):
            raise FusionlogError(f"{self.path}: the first block of runs starts at run {first}")
        self._structure = _Structure(times, dims, self._last_run_end(cids))
        return self._structure

    def _recorded_structure(self, cids: set[int], topic_of: dict[int, str]) -> _Structure | None:
        """The structure a fusionlog writer recorded (steps, runs, dt in `fusionlog.scenario`),
        checked against the file's last block and first messages, so that a long one-run log
        is not decoded twice (once to learn its steps, once to read it). None: scan instead."""
        meta = self.metadata.get("fusionlog.scenario", {})
        try:
            steps, runs, dt = int(meta["steps"]), int(meta["runs"]), float(meta["dt"])
        except (KeyError, ValueError):
            return None
        if runs != self._last_run_end(cids):
            return None
        dims: dict[str, int] = {}
        wanted = len({topic_of[c] for c in cids})
        for _, tab in self._tables(cids):
            _, at = np.unique(tab.cid, return_index=True)
            for i in sorted(at.tolist()):
                topic = topic_of[int(tab.cid[i])]
                if topic in dims:
                    continue
                if tab.off[i] != 0 or tab.step[i] != 0 or tab.time[i] != 0.0:
                    return None  # not the writer's order: fall back to the scan
                dims[topic] = int(tab.dim[i])
            if len(dims) == wanted:
                break
        # The writer's times are exactly these (np.arange(K + 1) * dt); the block reader checks
        # every message's step against 0..K, so a wrong record cannot go unnoticed.
        return _Structure(np.arange(steps + 1) * dt, dims, runs)

    def _last_run_end(self, cids: set[int]) -> int:
        """End of the last block of runs: the blocks are in order, so read only the last chunk."""
        candidates = [ci for ci, (_, ids) in enumerate(self._chunks) if ids is None or ids & cids]
        start = candidates[-1] if candidates and not self._linear else 0
        end = 0
        for _, tab in self._tables(cids, start):
            end = max(end, int((tab.off + tab.runs).max()))
        return end

    def schema_of(self, topic: str) -> str:
        """Schema name of ``topic`` (e.g. ``fusionlog.Block``)."""
        return self._info(topic).schema

    def kind_of(self, topic: str) -> str | None:
        """``"values"``, ``"estimate"``, or None for a topic fusionlog cannot read."""
        layout = self._info(topic).layout
        return layout.kind if layout is not None else None

    def dim_of(self, topic: str) -> int:
        """``dim`` of a topic's messages (state size n for estimates)."""
        self._readable(topic)
        dims = self._get_structure().dims
        if topic not in dims:
            raise FusionlogError(f"{self.path}: topic {topic} has no message in the first block")
        return dims[topic]

    def steps(self) -> int:
        """Number of time steps K + 1 (distinct steps of the first block of runs)."""
        return len(self._get_structure().times)

    def runs(self) -> int:
        """Total number of Monte Carlo runs in the file."""
        return self._get_structure().runs

    def times(self) -> np.ndarray:
        """(K + 1,) time in seconds of each step (first message of that step in the file)."""
        return self._get_structure().times.copy()

    def _info(self, topic: str) -> _TopicInfo:
        info = self._topics.get(topic)
        if info is None:
            have = ", ".join(sorted(self._topics)) or "none"
            raise FusionlogError(f"{self.path}: no topic {topic} (topics: {have})")
        return info

    def _readable(self, topic: str) -> _TopicInfo:
        info = self._info(topic)
        if info.layout is None:
            raise FusionlogError(
                f"{self.path}: topic {topic} has schema {info.schema or '(none)'} "
                f"({info.message_encoding}), not a fusionlog Block or EstimateBlock"
            )
        return info

    # -- blocks of runs ------------------------------------------------------------------------

    def iter_run_blocks(
        self, topics: Sequence[str], block_runs: int
    ) -> Iterator[tuple[int, int, dict[str, Any]]]:
        """Yield (run_offset, runs, {topic: data}) for consecutive blocks of ``block_runs`` runs.

        A values topic gives an array (runs, K+1, dim); an estimate topic gives (mean, cov) with
        mean (runs, K+1, n) and cov (K+1, n, n) if every message of this block had one shared
        covariance (the same across the file's blocks), else (runs, K+1, n, n).

        Memory stays around two output blocks plus two chunks, whatever the file's block size:
        the file is read sequentially, and a file block larger than the output window is read
        again for each window (where it starts is remembered, its bytes are not). Each chunk is
        decoded into columns (``_table``) and copied into the output blocks with a few numpy
        operations per topic (``_Assembly``), so no Python runs per message here.
        """
        if block_runs < 1:
            raise ValueError("block_runs must be >= 1")
        names = list(dict.fromkeys(topics))
        if not names:
            raise ValueError("no topics to read")
        infos = [self._readable(t) for t in names]
        st = self._get_structure()
        total = st.runs
        tidx = {cid: ti for ti, info in enumerate(infos) for cid in info.channel_ids}
        cids = set(tidx)
        topic_index = np.zeros(max(cids) + 1, np.int64)
        topic_index[list(tidx)] = list(tidx.values())
        kinds = [i.layout.kind for i in infos]  # type: ignore[union-attr]
        dims = [self.dim_of(t) for t in names]
        asm = _Assembly(
            self.path, names, dims, kinds, topic_index, len(st.times), total, block_runs
        )
        tables = self._tables(cids)
        try:
            cur: _Cursor = (next(tables, None), 0)
            expected = 0
            while cur[0] is not None:
                (ci, tab), row = cur
                o, r = int(tab.off[row]), int(tab.runs[row])
                topic = names[topic_index[tab.cid[row]]]
                if o != expected:
                    raise asm.bad(
                        f"{topic}: block of runs at run {o} where run {expected} was expected"
                    )
                if r < 1 or o + r > total:
                    raise asm.bad(f"{topic}: block at run {o} has {r} runs of {total}")
                b = asm.add_blocks(o + r)
                start = (ci, row)
                cur = asm.read_block(tables, cur, _Window(o, r, o, b, True))
                yield from asm.finished(b)
                # A file block wider than the window: read it again for each further window.
                while b < o + r:
                    a, b = b, asm.add_blocks(o + r)
                    again = self._tables(cids, start[0])
                    try:
                        asm.read_block(again, (next(again), start[1]), _Window(o, r, a, b, False))
                    finally:
                        again.close()
                    yield from asm.finished(b)
                expected = o + r
        finally:
            tables.close()
        if expected != total:
            raise asm.bad(f"the requested topics cover runs 0..{expected} of {total}")

    def read_all(self, topics: Sequence[str]) -> dict[str, Any]:
        """All runs of ``topics`` at once (small files, tests); same shapes as iter_run_blocks."""
        total = self.runs()
        for _, _, data in self.iter_run_blocks(topics, max(total, 1)):
            return data
        return {}


# --------------------------------------------------------------------------------------------
# Recovery
# --------------------------------------------------------------------------------------------


def recover(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What is still readable from a damaged (e.g. truncated) file, for ``inspect --recover``.

    Reads records sequentially up to the first damage (a seeking reader needs the footer, which
    a truncated file lacks). Returns a dict with ``error`` (why reading stopped, None if the
    file read to its end), ``library``, ``metadata``, ``schemas`` {topic: schema name},
    ``topics`` {topic: messages read}, ``messages``, ``steps`` (distinct steps of the first
    block of runs), ``complete_runs`` (runs whose block was read in full for every fusionlog
    topic), ``last_complete_step`` (last step k such that every fusionlog topic has steps 0..k
    in the last block read; -1 if none) and ``last_complete_time``.
    """
    p = Path(path)
    out: dict[str, Any] = {
        "path": str(p),
        "error": None,
        "library": None,
        "metadata": {},
        "schemas": {},
        "topics": {},
        "messages": 0,
        "steps": 0,
        "complete_runs": 0,
        "last_complete_step": -1,
        "last_complete_time": None,
    }
    schemas: dict[int, Schema] = {}
    channels: dict[int, tuple[str, _Layout | None]] = {}
    readable: set[str] = set()  # topics with a fusionlog layout
    # The block of runs being read: (run_offset, runs) and {topic: {step: time}}.
    block: tuple[int, int] | None = None
    seen: dict[str, dict[int, float]] = {}
    first_steps: set[int] | None = None

    def close_block() -> None:
        nonlocal first_steps
        if block is None:
            return
        if first_steps is None:
            first_steps = set().union(*(s.keys() for s in seen.values()))
        if all(first_steps <= seen.get(t, {}).keys() for t in readable):
            out["complete_runs"] += block[1]

    try:
        with open(p, "rb") as f:
            for rec in StreamReader(f).records:
                if isinstance(rec, Message):
                    if rec.channel_id not in channels:
                        continue
                    topic, layout = channels[rec.channel_id]
                    out["messages"] += 1
                    out["topics"][topic] += 1
                    if layout is None:
                        continue
                    step, t, off, runs, _, _, _ = _decode(rec.data, layout)
                    if block is None or block[0] != off:
                        close_block()
                        block, seen = (off, runs), {}
                    seen.setdefault(topic, {})[step] = t
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    schema = schemas.get(rec.schema_id)
                    layout = None
                    if schema is not None and rec.message_encoding == "protobuf":
                        layout = _layout_from_schema(schema)
                    channels[rec.id] = (rec.topic, layout)
                    out["schemas"][rec.topic] = schema.name if schema is not None else ""
                    out["topics"].setdefault(rec.topic, 0)
                    if layout is not None:
                        readable.add(rec.topic)
                elif isinstance(rec, Metadata):
                    out["metadata"][rec.name] = dict(rec.metadata)
                elif isinstance(rec, Header):
                    out["library"] = rec.library
    except OSError as e:
        raise _open_error(p, e) from e
    except Exception as e:  # whatever the damage looks like, report what came before it
        out["error"] = _one_line(e)
    close_block()
    out["steps"] = len(first_steps or ())
    if block is not None:
        k = -1
        while readable and all(k + 1 in seen.get(t, {}) for t in readable):
            k += 1
        out["last_complete_step"] = k
        if k >= 0:
            out["last_complete_time"] = next(iter(seen.values()))[k]
    return out
