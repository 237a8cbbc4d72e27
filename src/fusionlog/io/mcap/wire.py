"""The protobuf wire codec of ``fusionlog.Block`` / ``fusionlog.EstimateBlock``: the one encoder
(the writer and the tests both use it) and the one-message decoder.

Messages are encoded and decoded on the protobuf wire format directly (varint scalars, packed
doubles straight from/to ``ndarray`` bytes) instead of through protobuf message classes, whose
per-element handling of repeated fields costs several times more. A packed ``repeated double``
is on the wire a key, a length and raw little-endian float64, so ``ndarray.tobytes()`` is the
payload as it is.

Encoding gives the bytes ``SerializeToString`` of the official class gives (fields in number
order and, like every proto3 writer, zero scalars and empty repeated fields left out). It is
split in three pieces so that the writer can cache what changes only per step (step and time)
and per block of runs (run_offset, runs, dim and the payload keys and lengths) and join them
with the payloads per message.

Decoding matches fields by name and type in the file's own schema, not by the numbers above,
so a foreign writer's schema with the same fields (any numbers, proto2 or proto3, packed or
not, any field order, unknown fields) is read correctly; canonical encodings take a regex fast
path (the regex engine runs in C).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from fusionlog.core.reference import reference_paths

from .schema import (
    ESTIMATE,
    ESTIMATE_SCHEMA,
    HEADER_FIELDS,
    LABEL_REPEATED,
    OPTIONAL_PAYLOADS,
    PAYLOAD_FIELDS,
    SENSOR_SCHEMA,
    TYPE_DOUBLE,
    VALUES,
    file_descriptor_set,
    message_fields,
)

__all__ = [
    "UINT32_MAX",
    "Decoded",
    "Fields",
    "MessageFormat",
    "WireError",
    "decode",
    "decode_fields",
    "decode_message",
    "encode_block_fields",
    "encode_estimate_message",
    "encode_message",
    "encode_payload2_key",
    "encode_step_time",
    "encode_values_message",
    "format_for_schema",
    "format_of_schema_record",
    "payload_span",
]

UINT32_MAX = 2**32 - 1
_F64 = struct.Struct("<d")

# Wire types (protobuf encoding spec).
_VARINT, _FIXED64, _LEN, _FIXED32 = 0, 1, 2, 5

_NUMBER = {name: number for name, number, _ in HEADER_FIELDS}


def _key(number: int, wire_type: int) -> int:
    return number << 3 | wire_type


# --------------------------------------------------------------------------------------------
# Encoding
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


def _key_bytes(number: int, wire_type: int) -> bytes:
    return _varint(_key(number, wire_type))


_K_STEP = _key_bytes(_NUMBER["step"], _VARINT)
_K_TIME = _key_bytes(_NUMBER["time"], _FIXED64)
_K_RUN_OFFSET = _key_bytes(_NUMBER["run_offset"], _VARINT)
_K_RUNS = _key_bytes(_NUMBER["runs"], _VARINT)
_K_DIM = _key_bytes(_NUMBER["dim"], _VARINT)
# Both kinds number their payloads the same (6, then 7), so one pair of keys serves both.
assert PAYLOAD_FIELDS[VALUES][0][1] == PAYLOAD_FIELDS[ESTIMATE][0][1]
_K_P1 = _key_bytes(PAYLOAD_FIELDS[ESTIMATE][0][1], _LEN)
_K_P2 = _key_bytes(PAYLOAD_FIELDS[ESTIMATE][1][1], _LEN)
_ZERO8 = b"\x00" * 8


def encode_step_time(step: int, time: float) -> bytes:
    """The ``step`` and ``time`` fields (each left out when zero; -0.0 has its sign bit set
    and is written, as protobuf does)."""
    out = _K_STEP + _varint(step) if step else b""
    t = _F64.pack(time)
    return out + _K_TIME + t if t != _ZERO8 else out


def encode_block_fields(run_offset: int, runs: int, dim: int, payload1_len: int) -> bytes:
    """The ``run_offset``, ``runs`` and ``dim`` fields and the key and length of the first
    payload (``values`` or ``mean``), whose ``payload1_len`` bytes must follow."""
    parts = []
    if run_offset:
        parts += (_K_RUN_OFFSET, _varint(run_offset))
    if runs:
        parts += (_K_RUNS, _varint(runs))
    if dim:
        parts += (_K_DIM, _varint(dim))
    if payload1_len:
        parts += (_K_P1, _varint(payload1_len))
    return b"".join(parts)


def encode_payload2_key(payload2_len: int) -> bytes:
    """The key and length of the second payload (``covariance``); empty when there is none."""
    return _K_P2 + _varint(payload2_len) if payload2_len else b""


def encode_message(
    step: int,
    time: float,
    run_offset: int,
    runs: int,
    dim: int,
    payload1: bytes,
    payload2: bytes = b"",
) -> bytes:
    """Wire bytes of one message: the three pieces above joined with the payloads."""
    return b"".join(
        (
            encode_step_time(step, time),
            encode_block_fields(run_offset, runs, dim, len(payload1)),
            payload1,
            encode_payload2_key(len(payload2)),
            payload2,
        )
    )


def encode_values_message(
    step: int, time: float, run_offset: int, values: np.ndarray
) -> tuple[bytes, int, int]:
    """Wire bytes of one ``fusionlog.Block``; returns (data, runs, dim)."""
    v = np.ascontiguousarray(values, dtype="<f8")
    if v.ndim != 2 or v.shape[0] < 1:
        raise ValueError(f"values must have shape (runs >= 1, dim), got {v.shape}")
    runs, dim = v.shape
    return encode_message(step, time, run_offset, runs, dim, v.tobytes()), runs, dim


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
    return encode_message(step, time, run_offset, runs, n, m.tobytes(), c.tobytes()), runs, n


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------

# Actions of a wire key in a MessageFormat.
_A_STEP, _A_RUN_OFFSET, _A_RUNS, _A_DIM, _A_TIME, _A_P1, _A_P2, _A_P3 = range(8)
_INT_FIELDS = ("step", "run_offset", "runs", "dim")

Decoded = tuple[int, float, int, int, int, Any, Any]
"""(step, time, run_offset, runs, dim, payload1, payload2); payloads are bytes-like, LE doubles."""

Pieces = list[tuple[int, int]]
Fields = tuple[int, float, int, int, int, Pieces, Pieces, Pieces]
"""(step, time, run_offset, runs, dim, pieces1, pieces2, pieces3): a payload as (start, end) byte
ranges of the message, usually one; several when a writer split the packed field or did not
pack it. The third is a Block's ``arrival`` (`schema.PAYLOAD_FIELDS`), empty for an estimate."""


class WireError(Exception):
    """Malformed protobuf bytes (the reader turns it into a FusionlogError naming file and
    topic)."""


@dataclass(frozen=True)
class MessageFormat:
    """How to decode the messages of one schema.

    ``kind`` is VALUES or ESTIMATE; ``keys`` maps a wire key (field number << 3 | wire type) to
    what it holds; ``fast`` matches the five scalars of a canonical encoding (fields in number
    order, one-byte keys), None if the schema's numbers do not allow it; ``p1_key``..``p3_key``
    are the packed payloads' keys (-1: none), in `schema.PAYLOAD_FIELDS` order.
    """

    kind: str
    keys: dict[int, int]
    fast: re.Pattern[bytes] | None = None
    p1_key: int = -1
    p2_key: int = -1
    p3_key: int = -1


_VARINT_RE = rb"([\x80-\xff]{0,9}[\x00-\x7f])"


def _fast_pattern(numbers: dict[str, int], payload: list[str]) -> re.Pattern[bytes] | None:
    """Regex for the canonical encoding (fields in number order, one-byte keys), else None.

    Matching the five scalars this way costs a fraction of the Python loop in
    ``_fields_generic``; anything unusual falls back to that loop. Groups 1..5 are step, time,
    run_offset, runs, dim (each optional, as proto3 leaves zeros out).
    """
    order = ["step", "time", "run_offset", "runs", "dim", *payload]
    nums = [numbers[n] for n in order]
    if nums != sorted(nums) or len(set(nums)) != len(nums) or nums[-1] > 15:
        return None
    parts = []
    for name in order[:5]:
        key = re.escape(bytes([_key(numbers[name], _FIXED64 if name == "time" else _VARINT)]))
        parts.append(b"(?:" + key + (b"(.{8})" if name == "time" else _VARINT_RE) + b")?")
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
            raise WireError("varint longer than 10 bytes")


def _varint_value(b: bytes) -> int:
    if len(b) == 2:  # steps 128..16383: most messages of a long log
        return (b[0] & 0x7F) | b[1] << 7
    result = 0
    for i, byte in enumerate(b):
        result |= (byte & 0x7F) << (7 * i)
    return result


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
    pieces: tuple[Pieces, Pieces, Pieces] = ([], [], [])
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
            if wt == _VARINT:
                v = buf[pos]
                pos += 1
                if v >= 0x80:
                    v, pos = _read_varint(buf, pos - 1)
                if action is not None:
                    ints[action] = v
            elif wt == _LEN:
                ln = buf[pos]
                pos += 1
                if ln >= 0x80:
                    ln, pos = _read_varint(buf, pos - 1)
                end = pos + ln
                if end > n:
                    raise WireError("length-delimited field runs past the end")
                if action is not None:
                    if ln % 8:
                        raise WireError("packed double field length is not a multiple of 8")
                    pieces[action - _A_P1].append((pos, end))
                pos = end
            elif wt == _FIXED64:
                if pos + 8 > n:
                    raise WireError("fixed64 field runs past the end")
                if action == _A_TIME:
                    t = _F64.unpack_from(buf, pos)[0]
                elif action is not None and action >= _A_P1:
                    pieces[action - _A_P1].append((pos, pos + 8))
                pos += 8
            elif wt == _FIXED32:
                pos += 4
            else:
                raise WireError(f"unsupported wire type {wt}")
        if pos != n:
            raise WireError("message ends inside a field")
    except IndexError:
        raise WireError("message ends inside a field") from None
    return ints[0], t, ints[1], ints[2], ints[3], *pieces


def payload_span(buf: Any, pos: int, n: int) -> tuple[int, int]:
    """(start, end) of the packed doubles of the length-delimited field whose one-byte key is
    at ``pos`` of ``buf[:n]``; (-1, -1) if malformed."""
    ln = buf[pos + 1] if pos + 1 < n else 0x80
    pos += 2
    if ln >= 0x80:
        try:
            ln, pos = _read_varint(buf, pos - 1)
        except (IndexError, WireError):
            return -1, -1
    if pos + ln > n or ln % 8:
        return -1, -1
    return pos, pos + ln


def decode_fields(buf: Any, fmt: MessageFormat) -> Fields:
    """Decode one message's fields; canonical encodings take the regex fast path."""
    fast = fmt.fast
    if fast is not None:
        m = fast.match(buf)
        pos = m.end()  # type: ignore[union-attr]  # every group is optional: always matches
        n = len(buf)
        got: list[Pieces] = [[], [], []]
        for i, key in enumerate((fmt.p1_key, fmt.p2_key, fmt.p3_key)):  # key, length, doubles
            if 0 <= pos < n and buf[pos] == key:
                a, pos = payload_span(buf, pos, n)
                got[i] = [(a, pos)]
        if pos == n:  # -1 when a payload was malformed
            gs, gt, go, gr, gd = m.groups()  # type: ignore[union-attr]
            return (
                0 if gs is None else gs[0] if len(gs) == 1 else _varint_value(gs),
                0.0 if gt is None else _F64.unpack(gt)[0],
                0 if go is None else go[0] if len(go) == 1 else _varint_value(go),
                0 if gr is None else gr[0] if len(gr) == 1 else _varint_value(gr),
                0 if gd is None else gd[0] if len(gd) == 1 else _varint_value(gd),
                *got,
            )
    return _fields_generic(buf, fmt.keys)


def decode(buf: Any, fmt: MessageFormat) -> Decoded:
    """Decode one message, payloads as bytes-like (views of ``buf`` where they are contiguous)."""
    step, t, off, runs, dim, q1, q2, _ = decode_fields(buf, fmt)
    return step, t, off, runs, dim, _join(buf, q1), _join(buf, q2)


#: fusionlog's own schemas' kinds: a schema record byte for byte the one fusionlog writes is
#: read from `schema.message_fields`, without parsing it (nor importing google.protobuf).
_OWN = {SENSOR_SCHEMA: VALUES, ESTIMATE_SCHEMA: ESTIMATE}
_INT_TYPES = {13, 4, 5, 3}  # TYPE_UINT32, TYPE_UINT64, TYPE_INT32, TYPE_INT64


def format_of_schema_record(encoding: str, name: str, data: bytes) -> MessageFormat | None:
    """The format of a protobuf schema whose message ``name`` has the fusionlog fields, else None.

    Matching is by field name and type, not by schema name or number, so a foreign writer's
    schema with the same fields (any numbers, proto2 or proto3) is read correctly.
    """
    if encoding != "protobuf":
        return None
    if name in _OWN and data == file_descriptor_set():
        return _format_of_fields({f[0]: f[1:] for f in message_fields(_OWN[name])})
    fields = _parse_fields(name, data)
    return None if fields is None else _format_of_fields(fields)


def _parse_fields(name: str, data: bytes) -> dict[str, tuple[int, int, int]] | None:
    """{field name: (number, type, label)} of message ``name`` of a FileDescriptorSet, or None."""
    from google.protobuf import descriptor_pb2  # a foreign schema only: ~20 ms to import

    try:
        fds = descriptor_pb2.FileDescriptorSet.FromString(data)
    except Exception:
        return None
    msg = None
    for fdp in fds.file:
        stack = [
            (f"{fdp.package}.{m.name}" if fdp.package else m.name, m) for m in fdp.message_type
        ]
        while stack and msg is None:
            full, m = stack.pop()
            if full == name:
                msg = m
            stack.extend((f"{full}.{nm.name}", nm) for nm in m.nested_type)
        if msg is not None:
            break
    if msg is None:
        return None
    return {f.name: (f.number, f.type, f.label) for f in msg.field}


def _format_of_fields(fields: dict[str, tuple[int, int, int]]) -> MessageFormat | None:
    """The format of a message with these fields (`_parse_fields`), else None."""
    keys: dict[int, int] = {}
    for action, fname in enumerate(_INT_FIELDS):
        f = fields.get(fname)
        if f is None or f[1] not in _INT_TYPES or f[2] == LABEL_REPEATED:
            return None
        keys[_key(f[0], _VARINT)] = action
    f = fields.get("time")
    if f is None or f[1] != TYPE_DOUBLE or f[2] == LABEL_REPEATED:
        return None
    keys[_key(f[0], _FIXED64)] = _A_TIME
    kinds = [
        k
        for k in (VALUES, ESTIMATE)
        if all(p in fields or p in OPTIONAL_PAYLOADS[k] for p, _ in PAYLOAD_FIELDS[k])
    ]
    if not kinds:
        return None
    kind = kinds[0]
    payload = [p for p, _ in PAYLOAD_FIELDS[kind] if p in fields]
    action_of = {p: _A_P1 + i for i, (p, _) in enumerate(PAYLOAD_FIELDS[kind])}  # by name
    for pname in payload:
        action, f = action_of[pname], fields[pname]
        if f[1] != TYPE_DOUBLE or f[2] != LABEL_REPEATED:
            return None
        keys[_key(f[0], _LEN)] = action  # packed
        keys[_key(f[0], _FIXED64)] = action  # unpacked, one double per key
    numbers = {n: fields[n][0] for n in ("step", "time", *_INT_FIELDS[1:], *payload)}
    # the reference switch (`core.reference`): every message decoded field by field
    fast = None if reference_paths() else _fast_pattern(numbers, payload)
    pkeys = [-1, -1, -1]
    for p in payload:
        pkeys[action_of[p] - _A_P1] = _key(numbers[p], _LEN)
    return MessageFormat(kind, keys, fast, *pkeys)


@lru_cache(maxsize=2)
def format_for_schema(schema_name: str) -> MessageFormat:
    """The format of fusionlog's own schema ``schema_name`` (SENSOR_SCHEMA or ESTIMATE_SCHEMA)."""
    fmt = None
    if schema_name in (SENSOR_SCHEMA, ESTIMATE_SCHEMA):
        fmt = format_of_schema_record("protobuf", schema_name, file_descriptor_set())
    if fmt is None:
        raise ValueError(f"unknown fusionlog schema {schema_name!r}")
    return fmt


def decode_message(data: bytes, schema_name: str = SENSOR_SCHEMA) -> dict[str, Any]:
    """Decode one fusionlog message (bytes) into a dict of fields, payloads reshaped.

    For debugging and tests; the reader uses the same decoder without building dicts.
    """
    fmt = format_for_schema(schema_name)
    step, t, off, runs, dim, p1, p2 = decode(data, fmt)
    out: dict[str, Any] = {"step": step, "time": t, "run_offset": off, "runs": runs, "dim": dim}
    a1 = np.frombuffer(p1, dtype="<f8")
    if fmt.kind == VALUES:
        out["values"] = a1.reshape(runs, dim)
        if p2:
            out["covariance"] = np.frombuffer(p2, dtype="<f8").reshape(runs, dim, dim)
    else:
        a2 = np.frombuffer(p2, dtype="<f8")
        out["mean"] = a1.reshape(runs, dim)
        out["covariance"] = a2.reshape((dim, dim) if a2.size == dim * dim else (runs, dim, dim))
    return out
