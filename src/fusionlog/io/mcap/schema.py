"""The two protobuf message types of fusionlog's MCAP files (DESIGN.md, "MCAP files").

Both live in the proto3 package ``fusionlog`` of the file ``fusionlog/blocks.proto``::

    message Block         { uint32 step = 1; double time = 2; uint32 run_offset = 3;
                            uint32 runs = 4; uint32 dim = 5; repeated double values = 6;
                            repeated double covariance = 7; repeated double arrival = 8; }
    message EstimateBlock { uint32 step = 1; double time = 2; uint32 run_offset = 3;
                            uint32 runs = 4; uint32 dim = 5; repeated double mean = 6;
                            repeated double covariance = 7; }

``values`` is (runs, dim) and ``mean`` is (runs, n), row-major; ``covariance`` is (n, n) when it
is the same for every run of the message and (runs, n, n) otherwise. A Block's ``covariance``
is optional: the measurement noise covariance (dim, dim) of a reading whose R varies from
message to message (a recorded log that carries its own covariances); absent, the sensor's R
applies. Its optional ``arrival`` is when the readings reached the filters (seconds, one value,
or one per run when the delays differ: DESIGN.md "Late measurements"); absent, on time.
Files written before the fields existed decode the same. The field numbers are
defined here once; the wire codec (:mod:`.wire`) derives its tags from them. The schema is
embedded in every file as a FileDescriptorSet built at run time (no protoc), so any MCAP +
protobuf reader decodes the files without fusionlog. Its bytes are encoded here directly (a
few nested length-delimited fields), as ``descriptor_pb2`` serialises them: importing
``google.protobuf`` costs ~20 ms of every command's start, and only `protobuf_classes` (tests,
third-party checks) and foreign schemas (`wire.format_of_schema_record`) need it.
"""

from __future__ import annotations

from functools import lru_cache

__all__ = [
    "ESTIMATE",
    "ESTIMATE_SCHEMA",
    "HEADER_FIELDS",
    "OPTIONAL_PAYLOADS",
    "PAYLOAD_FIELDS",
    "PROTO_FILE",
    "SENSOR_SCHEMA",
    "VALUES",
    "file_descriptor_set",
    "message_fields",
    "protobuf_classes",
]

SENSOR_SCHEMA = "fusionlog.Block"
ESTIMATE_SCHEMA = "fusionlog.EstimateBlock"
PROTO_FILE = "fusionlog/blocks.proto"

#: Kinds of topic: a Block carries values, an EstimateBlock a mean and a covariance.
VALUES = "values"
ESTIMATE = "estimate"

#: FieldDescriptorProto's Type and Label values (descriptor.proto) of the fields used here.
TYPE_DOUBLE, TYPE_UINT32 = 1, 13
LABEL_OPTIONAL, LABEL_REPEATED = 1, 3

#: (name, field number, protobuf type) of the scalar fields every message starts with.
HEADER_FIELDS: tuple[tuple[str, int, int], ...] = (
    ("step", 1, TYPE_UINT32),
    ("time", 2, TYPE_DOUBLE),
    ("run_offset", 3, TYPE_UINT32),
    ("runs", 4, TYPE_UINT32),
    ("dim", 5, TYPE_UINT32),
)

#: Per kind: (name, field number) of its packed ``repeated double`` payloads, in order.
PAYLOAD_FIELDS: dict[str, tuple[tuple[str, int], ...]] = {
    VALUES: (("values", 6), ("covariance", 7), ("arrival", 8)),
    ESTIMATE: (("mean", 6), ("covariance", 7)),
}
#: The payloads a schema of the kind may lack (older Blocks have no covariance or arrival).
OPTIONAL_PAYLOADS: dict[str, tuple[str, ...]] = {
    VALUES: ("covariance", "arrival"),
    ESTIMATE: (),
}

_MESSAGES = ((SENSOR_SCHEMA, VALUES), (ESTIMATE_SCHEMA, ESTIMATE))


#: The payload only the sensors files of late sensors declare (their schema says ``arrival``;
#: every other file's schema is as it was before the field existed, byte for byte).
LATE_ONLY = "arrival"


def message_fields(kind: str, arrival: bool = False) -> list[tuple[str, int, int, int]]:
    """(name, number, type, label) of the fields of the message of a kind, in number order;
    a Block's ``arrival`` where `arrival` (a sensors file with late sensors)."""
    return [(n, num, t, LABEL_OPTIONAL) for n, num, t in HEADER_FIELDS] + [
        (n, num, TYPE_DOUBLE, LABEL_REPEATED)
        for n, num in PAYLOAD_FIELDS[kind]
        if arrival or n != LATE_ONLY
    ]


def _varint(v: int) -> bytes:
    out = bytearray()
    while v >= 0x80:
        out.append(v & 0x7F | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def _len_field(number: int, data: bytes) -> bytes:
    """A length-delimited field (a string or an embedded message)."""
    return _varint(number << 3 | 2) + _varint(len(data)) + data


def _int_field(number: int, v: int) -> bytes:
    return _varint(number << 3) + _varint(v)


@lru_cache(maxsize=2)
def file_descriptor_set(arrival: bool = False) -> bytes:
    """Serialized FileDescriptorSet embedded as the schema data of both schemas: the proto3
    file holding both message types (FileDescriptorProto: name 1, package 2, message_type 4,
    syntax 12; DescriptorProto: name 1, field 2; FieldDescriptorProto: name 1, number 3,
    label 4, type 5), fields in number order as protobuf serialises them; with the Block's
    ``arrival`` where `arrival`."""
    messages = b""
    for full_name, kind in _MESSAGES:
        fields = b"".join(
            _len_field(2, _len_field(1, n.encode()) + _int_field(3, num) + _int_field(4, lab)
                       + _int_field(5, typ))
            for n, num, typ, lab in message_fields(kind, arrival)
        )  # fmt: skip
        messages += _len_field(4, _len_field(1, full_name.rsplit(".", 1)[1].encode()) + fields)
    fdp = (
        _len_field(1, PROTO_FILE.encode())
        + _len_field(2, b"fusionlog")
        + messages
        + _len_field(12, b"proto3")
    )
    return _len_field(1, fdp)  # FileDescriptorSet.file


@lru_cache(maxsize=1)
def protobuf_classes() -> tuple[type, type]:
    """Official protobuf classes (Block, EstimateBlock) for tests and third-party style checks."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    pool.Add(descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set()).file[0])
    return (
        message_factory.GetMessageClass(pool.FindMessageTypeByName(SENSOR_SCHEMA)),
        message_factory.GetMessageClass(pool.FindMessageTypeByName(ESTIMATE_SCHEMA)),
    )
