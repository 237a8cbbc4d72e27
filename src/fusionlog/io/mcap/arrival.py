"""The ``arrival`` field of a sensor message (DESIGN.md "Late measurements"): when its readings
reached the filters, in seconds -- one value, or one per run when the delays differ.

The field is the Block's third payload (`schema.PAYLOAD_FIELDS`), written after the others and
left out for a reading on time; the block reader skips it (it decodes values and covariance),
so the arrivals are read here, in a pass of their own over the sensor topics that have them.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence

import numpy as np
from mcap.reader import make_reader

from .schema import PAYLOAD_FIELDS, VALUES
from .wire import _A_P1, _A_P2, _LEN, _fields_generic, _join, _key, _varint, format_for_schema

__all__ = ["arrival_field", "iter_arrival_blocks", "read_arrivals"]

_NUMBER = dict(PAYLOAD_FIELDS[VALUES])["arrival"]
_KEY = _varint(_key(_NUMBER, _LEN))


def arrival_field(arrival: np.ndarray | float) -> bytes:
    """The wire bytes of the ``arrival`` field: its key, length and packed doubles."""
    data = np.asarray(arrival, dtype="<f8").ravel().tobytes()
    return _KEY + _varint(len(data)) + data


def _arrival_messages(
    path: str | os.PathLike[str], topics: Sequence[str]
) -> Iterator[tuple[str, int, int, int, np.ndarray]]:
    """(topic, step, run_offset, runs, arrivals) of each message of `topics` that carries an
    arrival field, in log-time order."""
    keys = dict(format_for_schema("fusionlog.Block").keys)
    keys = {k: a for k, a in keys.items() if a < _A_P1}  # the header fields only
    keys[_key(_NUMBER, _LEN)] = _A_P2
    keys[_key(_NUMBER, 1)] = _A_P2  # unpacked doubles
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=list(topics)):
            data = message.data
            step, _, off, r, _, _, pieces = _fields_generic(data, keys)
            if pieces:
                yield channel.topic, step, off, r, np.frombuffer(_join(data, pieces), dtype="<f8")


def read_arrivals(
    path: str | os.PathLike[str], topics: Sequence[str], runs: int, instants: int
) -> dict[str, np.ndarray | None]:
    """Each topic's arrival times (runs, K+1) in seconds, NaN at instants without a message;
    None for a topic none of whose messages carries one (its readings were on time)."""
    out: dict[str, np.ndarray | None] = dict.fromkeys(topics)
    for topic, step, off, r, a in _arrival_messages(path, topics):
        arr = out[topic]
        if arr is None:
            arr = out[topic] = np.full((runs, instants), np.nan)
        arr[off : off + r, step] = a if len(a) == r else a[0]
    return out


def iter_arrival_blocks(
    path: str | os.PathLike[str], topics: Sequence[str], instants: int, block: int
) -> Iterator[tuple[int, int, np.ndarray]]:
    """A one-run file's arrival times block of time by block (issue 34): (k0, k1, (k1 - k0,
    len(topics)) s) for consecutive windows of `block` instants, NaN where a topic has no
    message carrying one (`read_arrivals`' values, the whole run never held)."""
    col = {t: c for c, t in enumerate(topics)}
    k0 = 0
    cur = np.full((min(block, instants), len(topics)), np.nan)
    for topic, step, _, _, a in _arrival_messages(path, topics):
        if step < k0 or step >= instants:
            raise ValueError(f"{path}: {topic}: step {step} out of order")
        while step >= k0 + block:
            yield k0, k0 + len(cur), cur
            k0 += block
            cur = np.full((min(block, instants - k0), len(topics)), np.nan)
        cur[step - k0, col[topic]] = a[0]
    while k0 < instants:
        yield k0, k0 + len(cur), cur
        k0 += block
        cur = np.full((max(0, min(block, instants - k0)), len(topics)), np.nan)
