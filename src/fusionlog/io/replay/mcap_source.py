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
from math import isqrt
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Schema

from .decoders import SUPPORTED, decoder_factories
from .fields import (
    FieldPath,
    PathError,
    describe,
    is_array,
    parse_path,
    to_number,
    to_time_ns,
)
from .series import Collector, Series, fail
from .topics import TopicInfo, catalog, damaged, one_line, open_mcap

__all__ = ["read_mcap"]


def _path(source: Path, what: str, text: str, key: str) -> FieldPath:
    try:
        return parse_path(text)
    except PathError as e:
        raise fail(source, what, f"{key}: {e}") from None


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


class _Covariance:
    """Extracts ``M[np.ix_(idx, idx)]`` from a flat row-major square matrix field."""

    def __init__(self, path: FieldPath, index: Sequence[int] | None, d: int) -> None:
        self.path, self.index, self.d = path, index, d
        self.n: int | None = None
        self.ix: Any = None

    def block(self, value: Any) -> np.ndarray:
        p = self.path.text
        if not is_array(value) or isinstance(value, bytes | bytearray | memoryview):
            raise PathError(f"covariance {p} is {describe(value)}, not an array of numbers")
        n = len(value)
        if self.n is None:
            k = isqrt(n)
            if n == 0 or k * k != n:
                raise PathError(f"covariance {p} has {n} numbers, not a square matrix")
            idx = list(range(k)) if self.index is None else list(self.index)
            if self.index is None and k != self.d:
                raise PathError(
                    f"covariance {p} is {k}x{k} but values has {self.d} components: give "
                    "covariance_index (its rows/columns that belong to values)"
                )
            bad = [i for i in idx if i >= k]
            if bad:
                raise PathError(
                    f"covariance_index {bad[0]} is out of range for the {k}x{k} matrix {p}"
                )
            self.n, self.ix = n, np.ix_(idx, idx)
        elif n != self.n:
            raise PathError(f"covariance {p} has {n} numbers where the first message had {self.n}")
        if all(type(x) is float for x in value):
            flat = np.array(value, dtype=np.float64)
        else:
            flat = np.array([to_number(x, f"{p}[{j}]") for j, x in enumerate(value)])
        k = isqrt(n)
        return flat.reshape(k, k)[self.ix]


def read_mcap(
    source: Path,
    *,
    topic: str,
    values: Sequence[str],
    time: str | None,
    time_unit: str,
    covariance: str | None,
    covariance_index: Sequence[int] | None,
    what: str,
) -> Series:
    vpaths = [_path(source, what, v, "values") for v in values]
    tpath = _path(source, what, time, "time") if time is not None else None
    cov = (
        _Covariance(_path(source, what, covariance, "covariance"), covariance_index, len(values))
        if covariance is not None
        else None
    )
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

        col = Collector(
            source, what, len(vpaths), cov is not None, "message", lambda k: f"message {k}"
        )
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
            try:
                vals = [to_number(p.resolve(decoded), p.text) for p in vpaths]
                if tpath is None:
                    t = message.log_time
                else:
                    t = to_time_ns(tpath.resolve(decoded), tpath.text, time_unit)
                block = cov.block(cov.path.resolve(decoded)) if cov is not None else None
            except PathError as e:
                name = schema.name if schema is not None else "schemaless"
                where = f"topic {topic} ({name})" + (f", message {k}" if k > 1 else "")
                raise fail(source, what, f"{where}: {e}") from None
            col.add(k, t, vals, block)
    if k == 0:
        raise fail(source, what, f"topic {topic} has no messages")
    return col.finish()
