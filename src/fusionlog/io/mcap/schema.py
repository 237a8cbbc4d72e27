"""The two protobuf message types of fusionlog's MCAP files (DESIGN.md, "MCAP files").

Both live in the proto3 package ``fusionlog`` of the file ``fusionlog/blocks.proto``::

    message Block         { uint32 step = 1; double time = 2; uint32 run_offset = 3;
                            uint32 runs = 4; uint32 dim = 5; repeated double values = 6;
                            repeated double covariance = 7; }
    message EstimateBlock { uint32 step = 1; double time = 2; uint32 run_offset = 3;
                            uint32 runs = 4; uint32 dim = 5; repeated double mean = 6;
                            repeated double covariance = 7; }

``values`` is (runs, dim) and ``mean`` is (runs, n), row-major; ``covariance`` is (n, n) when it
is the same for every run of the message and (runs, n, n) otherwise. A Block's ``covariance``
is optional: the measurement noise covariance (dim, dim) of a reading whose R varies from
message to message (a recorded log that carries its own covariances); absent, the sensor's R
applies. Files written before the field existed decode the same. The field numbers are
defined here once; the wire codec (:mod:`.wire`) derives its tags from them. The schema is
embedded in every file as a FileDescriptorSet built at run time (no protoc), so any MCAP +
protobuf reader decodes the files without fusionlog.
"""

from __future__ import annotations

from functools import lru_cache

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

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
    "protobuf_classes",
]

SENSOR_SCHEMA = "fusionlog.Block"
ESTIMATE_SCHEMA = "fusionlog.EstimateBlock"
PROTO_FILE = "fusionlog/blocks.proto"

#: Kinds of topic: a Block carries values, an EstimateBlock a mean and a covariance.
VALUES = "values"
ESTIMATE = "estimate"

_F = descriptor_pb2.FieldDescriptorProto

#: (name, field number, protobuf type) of the scalar fields every message starts with.
HEADER_FIELDS: tuple[tuple[str, int, int], ...] = (
    ("step", 1, _F.TYPE_UINT32),
    ("time", 2, _F.TYPE_DOUBLE),
    ("run_offset", 3, _F.TYPE_UINT32),
    ("runs", 4, _F.TYPE_UINT32),
    ("dim", 5, _F.TYPE_UINT32),
)

#: Per kind: (name, field number) of its packed ``repeated double`` payloads, in order.
PAYLOAD_FIELDS: dict[str, tuple[tuple[str, int], ...]] = {
    VALUES: (("values", 6), ("covariance", 7)),
    ESTIMATE: (("mean", 6), ("covariance", 7)),
}
#: The payloads a schema of the kind may lack (older Blocks have no covariance).
OPTIONAL_PAYLOADS: dict[str, tuple[str, ...]] = {VALUES: ("covariance",), ESTIMATE: ()}

_MESSAGES = ((SENSOR_SCHEMA, VALUES), (ESTIMATE_SCHEMA, ESTIMATE))


@lru_cache(maxsize=1)
def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The proto3 file holding both message types."""
    fdp = descriptor_pb2.FileDescriptorProto(name=PROTO_FILE, package="fusionlog", syntax="proto3")
    for full_name, kind in _MESSAGES:
        m = fdp.message_type.add(name=full_name.rsplit(".", 1)[1])
        for name, number, ftype in HEADER_FIELDS:
            m.field.add(name=name, number=number, type=ftype, label=_F.LABEL_OPTIONAL)
        for name, number in PAYLOAD_FIELDS[kind]:
            m.field.add(name=name, number=number, type=_F.TYPE_DOUBLE, label=_F.LABEL_REPEATED)
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
