"""The decoders every replay source uses: the ecosystem's, plus JSON.

``mcap-ros2-support`` decodes CDR with ``ros2msg`` schemas, ``mcap-protobuf-support`` protobuf
with FileDescriptorSet schemas. Neither package (nor ``mcap``) ships a decoder for
``message_encoding = "json"``, so :class:`JsonDecoderFactory` plugs ``json.loads`` into the same
``decoder_factories`` mechanism; its schema (JSON Schema, or none) is not needed to read fields.
Its non-integer numbers decode as :class:`decimal.Decimal` (the digits as written).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from decimal import Decimal
from typing import Any

from mcap.decoder import DecoderFactory
from mcap.records import Schema
from mcap.well_known import MessageEncoding
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

__all__ = ["JsonDecoderFactory", "SUPPORTED", "decoder_factories"]

SUPPORTED = "cdr (ros2msg schema), protobuf, json"


def _decode_json(data: bytes) -> Any:
    # numbers with a fraction or an exponent as Decimal: a time such as 1305031102.160407 s
    # becomes whole nanoseconds from its digits, never through a float (as in text tables)
    return json.loads(data, parse_float=Decimal)


class JsonDecoderFactory(DecoderFactory):
    """Decodes ``message_encoding = "json"`` with :func:`json.loads` (UTF-8/16/32)."""

    def decoder_for(
        self, message_encoding: str, schema: Schema | None
    ) -> Callable[[bytes], Any] | None:
        if message_encoding != MessageEncoding.JSON:
            return None
        return _decode_json


def decoder_factories() -> list[DecoderFactory]:
    """Fresh factories (they cache per schema id, which is per file)."""
    return [Ros2DecoderFactory(), ProtobufDecoderFactory(), JsonDecoderFactory()]
