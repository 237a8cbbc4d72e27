"""MCAP reading and writing for fusionlog's sensor and estimate streams.

The file format is the contract in DESIGN.md ("MCAP files"). One module per concern:

- :mod:`.schema`  the two protobuf message types, their field numbers, the FileDescriptorSet;
- :mod:`.wire`    the protobuf wire codec: the one encoder, the one-message decoder;
- :mod:`.writer`  McapWriter: messages in the documented order into a file object;
- :mod:`.layout`  the ``fusionlog.layout`` record the writer leaves for the reader;
- :mod:`.chunks`  MCAP records: opening, chunks, CRCs (the only user of mcap's internals);
- :mod:`.columns` many messages decoded at once into numpy columns;
- :mod:`.blocks`  decoded columns assembled into blocks of runs;
- :mod:`.file`    McapFile, the reading API;
- :mod:`.recover` what is still readable from a damaged file.
"""

from .chunks import read_metadata
from .file import McapFile
from .layout import LAYOUT_META
from .recover import recover
from .schema import (
    ESTIMATE,
    ESTIMATE_SCHEMA,
    PROTO_FILE,
    SENSOR_SCHEMA,
    VALUES,
    file_descriptor_set,
    protobuf_classes,
)
from .topics import TRUTH, arch_of, estimates_topic, sensor_topic
from .wire import (
    decode_message,
    encode_estimate_message,
    encode_message,
    encode_values_message,
)
from .writer import McapWriter

__all__ = [
    "TRUTH",
    "arch_of",
    "estimates_topic",
    "sensor_topic",
    "ESTIMATE",
    "ESTIMATE_SCHEMA",
    "LAYOUT_META",
    "PROTO_FILE",
    "SENSOR_SCHEMA",
    "VALUES",
    "McapFile",
    "McapWriter",
    "decode_message",
    "encode_estimate_message",
    "encode_message",
    "encode_values_message",
    "file_descriptor_set",
    "protobuf_classes",
    "read_metadata",
    "recover",
]
