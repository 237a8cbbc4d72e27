"""The ``arrival`` field of a sensor message (DESIGN.md "Late measurements"): when its readings
reached the filters, in seconds -- one value, or one per run when the delays differ.

The field is the Block's third payload (`schema.PAYLOAD_FIELDS`), written after the others and
left out for a reading on time; the block reader skips it (it decodes values and covariance),
so the arrivals are read here, in a pass of their own over the sensor topics that have them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from mcap.reader import make_reader

from .schema import PAYLOAD_FIELDS, VALUES
from .wire import _A_P1, _A_P2, _LEN, _fields_generic, _join, _key, _varint, format_for_schema

__all__ = ["arrival_field", "read_arrivals"]

_NUMBER = dict(PAYLOAD_FIELDS[VALUES])["arrival"]
_KEY = _varint(_key(_NUMBER, _LEN))


def arrival_field(arrival: np.ndarray | float) -> bytes:
    """The wire bytes of the ``arrival`` field: its key, length and packed doubles."""
    data = np.asarray(arrival, dtype="<f8").ravel().tobytes()
    return _KEY + _varint(len(data)) + data


def read_arrivals(
    path: str | os.PathLike[str], topics: Sequence[str], runs: int, instants: int
) -> dict[str, np.ndarray | None]:
    """Each topic's arrival times (runs, K+1) in seconds, NaN at instants without a message;
    None for a topic none of whose messages carries one (its readings were on time)."""
    keys = dict(format_for_schema("fusionlog.Block").keys)
    keys = {k: a for k, a in keys.items() if a < _A_P1}  # the header fields only
    keys[_key(_NUMBER, _LEN)] = _A_P2
    keys[_key(_NUMBER, 1)] = _A_P2  # unpacked doubles
    out: dict[str, np.ndarray | None] = dict.fromkeys(topics)
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(topics)):
            data = message.data
            step, _, off, r, _, _, pieces = _fields_generic(data, keys)
            if not pieces:
                continue
            a = np.frombuffer(_join(data, pieces), dtype="<f8")
            arr = out[channel.topic]
            if arr is None:
                arr = out[channel.topic] = np.full((runs, instants), np.nan)
            arr[off : off + r, step] = a if len(a) == r else a[0]
    return out
