"""Measurements from one topic of any MCAP file (ROS 2 CDR, protobuf, JSON).

Messages are decoded by the ecosystem's decoders through ``mcap``'s
``iter_decoded_messages`` (see :mod:`.decoders`) and read with field paths (:mod:`.fields`).
Before the first message, every channel of the topic must have a decoder: an unknown encoding or
a schema its decoder cannot parse is a one-line error naming the topic and encodings. Messages come
in log-time order; the measurement time is ``log_time`` or the ``time`` field.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from pathlib import Path

from mcap.records import Channel, Schema

from .decoders import SUPPORTED, decoder_factories
from .extract import Extractor, StreamFields
from .fields import leaf_fields
from .series import Series, fail
from .topic_listing import TopicInfo, catalog, damaged, one_line, open_mcap

__all__ = ["first_fields", "read_mcap"]


def _schema_text(channel: Channel, schema: Schema | None) -> str:
    if schema is None:
        return f"no schema, message encoding {channel.message_encoding!r}"
    return (
        f"schema {schema.name!r}, schema encoding {schema.encoding!r}, "
        f"message encoding {channel.message_encoding!r}"
    )


def _check_decodable(source: Path, what: str, info: TopicInfo, factories: list) -> None:
    """Every channel of the topic has a decoder whose schema parses."""
    for channel, schema in info.channels:
        for factory in factories:
            try:
                # the ROS 2 schema parser prints its own message before raising: ours says it
                with contextlib.redirect_stderr(io.StringIO()):
                    decoder = factory.decoder_for(channel.message_encoding, schema)
            except Exception as e:  # a schema the decoder cannot parse, whatever it raises
                raise fail(
                    source,
                    what,
                    f"topic {info.topic}: cannot decode its schema "
                    f"({_schema_text(channel, schema)}): {type(e).__name__}: {one_line(e)}",
                ) from None
            if decoder is not None:
                break
        else:
            raise fail(
                source,
                what,
                f"topic {info.topic}: no decoder for {_schema_text(channel, schema)} "
                f"(supported: {SUPPORTED})",
            )


def read_mcap(source: Path, *, topic: str, fields: StreamFields, what: str) -> Series:
    ex = Extractor(source, what, fields)
    factories = decoder_factories()
    with open_mcap(source, what, factories) as (reader, f):
        try:
            topics = catalog(reader, f)
        except Exception as e:  # a damaged file, whatever the library raises
            raise damaged(source, e, what) from None
        info = topics.get(topic)
        if info is None:
            have = ", ".join(sorted(topics)) or "none"
            raise fail(source, what, f"no topic {topic} in the file (topics: {have})")
        if not info.count:
            raise fail(source, what, f"topic {topic} has no messages")
        _check_decodable(source, what, info, factories)

        col = ex.collector()
        messages = reader.iter_decoded_messages(topics=[topic])
        k = 0
        while True:
            try:
                schema, channel, message, decoded = next(messages)
            except StopIteration:
                break
            except Exception as e:  # damaged container or message bytes
                ch = info.channels[0]
                raise damaged(
                    source,
                    e,
                    what,
                    f"message {k + 1} of topic {topic} ({_schema_text(*ch)})",
                ) from None
            k += 1
            name = schema.name if schema is not None else "schemaless"
            ex.add(col, k, decoded, message.log_time, topic, name)
    if k == 0:
        raise fail(source, what, f"topic {topic} has no messages")
    return col.finish()


def first_fields(
    source: Path, topics: Sequence[str]
) -> dict[str, list[tuple[str, str, str]] | str]:
    """For ``inspect``: per topic the field paths of its first decoded message with their types
    and values (:func:`.fields.leaf_fields`), or why it does not decode (a string)."""
    out: dict[str, list[tuple[str, str, str]] | str] = {}
    factories = decoder_factories()
    with open_mcap(source, None, factories) as (reader, f):
        try:
            info = catalog(reader, f)
        except Exception as e:  # a damaged file, whatever the library raises
            raise damaged(source, e) from None
        for topic in topics:
            if topic not in info or not info[topic].count:
                continue
            try:
                _check_decodable(source, "inspect", info[topic], factories)
                for _, _, _, decoded in reader.iter_decoded_messages(topics=[topic]):
                    out[topic] = leaf_fields(decoded)
                    break
            except Exception as e:  # no decoder, or the first message does not decode
                out[topic] = one_line(e).split("inspect: ", 1)[-1]
    return out
