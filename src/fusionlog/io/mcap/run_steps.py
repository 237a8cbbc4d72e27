"""The messages of one run over a window of instants, encoded at once with numpy (issue 34).

A one-run log of 10^6 instants is ~10^7 messages (four sensor topics, seven estimates).
Encoding them one by one (`McapWriter.write_values` / `write_estimate`: argument checks, the
bookkeeping, one ``bytes.join`` per message) cost ~5 µs each, most of the estimate stage.
Here the messages of a window are laid out as rows of a uint8 array, one row per instant:
for each topic in order, the step and time fields (:func:`.wire.encode_step_time`, whose
length changes only where the step's varint grows), the fields fixed for the topic
(:func:`.wire.encode_block_fields`, :func:`.wire.encode_payload2_key`) and the payload
doubles. The bytes are those of the one-message encoder (a test compares them), so the file
is the same byte for byte; what is left per message is slicing the joined bytes and the
channel's ``log`` call.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from .arrival import arrival_field
from .wire import _K_STEP, _K_TIME, UINT32_MAX, encode_block_fields, encode_payload2_key

__all__ = ["RunColumn", "encode_run_steps", "log_times", "present_runs"]

_U8 = np.uint8
_ARRIVAL_KEY = arrival_field(0.0)[:-8]  # what precedes a message's one arrival double


class RunColumn(NamedTuple):
    """One topic's messages at the window's instants (run_offset 0, one run): ``first`` (w, d)
    the values or the mean, ``second`` (w, d, d) the covariance or None, ``arrival`` (w,) when
    each sensor reading arrived (s, the Block's ``arrival`` field) or None: on time."""

    topic: str
    kind: str
    first: np.ndarray
    second: np.ndarray | None = None
    arrival: np.ndarray | None = None

    def rows(self, i: int, j: int) -> RunColumn:
        """The column at instants i..j-1 of its window."""

        def part(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[i:j]

        return self._replace(first=self.first[i:j], second=part(self.second),
                             arrival=part(self.arrival))  # fmt: skip


def present_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starts and ends [a, b) of the runs of True in `mask` (w,): the instants a topic has
    messages at."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def _varint_len(steps: np.ndarray) -> np.ndarray:
    """Bytes of each step's varint (0 for step 0, which proto3 leaves out with its key)."""
    n = np.zeros(len(steps), np.int64)
    for i in range(5):  # a uint32 has at most five 7-bit groups
        n += steps >= (1 << (7 * i))
    return n


def _heads(steps: np.ndarray, times: np.ndarray) -> list[tuple[int, int, np.ndarray]]:
    """(i, j, H): the step and time fields of instants i..j-1 as rows H (j - i, h) of equal
    length, for the runs of instants whose fields have the same length."""
    vlen = _varint_len(steps)
    has_time = times.view(np.uint64) != 0  # 0.0 is left out; -0.0 was made 0.0 by the caller
    code = vlen * 2 + has_time
    cut = np.flatnonzero(np.diff(code)) + 1
    out = []
    for i, j in zip([0, *cut.tolist()], [*cut.tolist(), len(steps)], strict=True):
        L, timed = int(vlen[i]), bool(has_time[i])
        parts = []
        if L:
            s = steps[i:j]
            parts.append(np.broadcast_to(np.frombuffer(_K_STEP, _U8), (j - i, len(_K_STEP))))
            groups = [(s >> (7 * g)) & 0x7F | (0x80 if g < L - 1 else 0) for g in range(L)]
            parts.append(np.stack(groups, axis=1).astype(_U8))
        if timed:
            parts.append(np.broadcast_to(np.frombuffer(_K_TIME, _U8), (j - i, len(_K_TIME))))
            parts.append(times[i:j, None].astype("<f8").view(_U8))
        h = np.concatenate(parts, axis=1) if parts else np.zeros((j - i, 0), _U8)
        out.append((i, j, h))
    return out


def encode_run_steps(
    k0: int, times: np.ndarray, columns: Sequence[RunColumn]
) -> tuple[bytes, np.ndarray]:
    """The wire bytes of the messages at instants k0..k0+w-1 (``times`` (w,) in seconds, finite
    and >= 0, -0.0 taken as 0.0), for each instant for each column in order, joined; and the
    w * len(columns) + 1 offsets where each message starts and the last ends."""
    w = len(times)
    steps = np.arange(k0, k0 + w, dtype=np.int64)
    if w and steps[-1] > UINT32_MAX:
        raise ValueError(f"step must fit in uint32, got {int(steps[-1])}")
    pieces = []  # per column: the fixed fields and payload arrays, in message order
    for c in columns:
        first = np.ascontiguousarray(c.first, dtype="<f8")
        if first.ndim != 2 or first.shape[0] != w:
            raise ValueError(f"{c.topic}: {w} rows of values expected, got {first.shape}")
        d = first.shape[1]
        second = b""
        cols = [first.view(_U8).reshape(w, 8 * d)]
        if c.second is not None:
            sec = np.ascontiguousarray(c.second, dtype="<f8").reshape(w, -1)
            second = sec.view(_U8)
            cols.append(second)
        if c.arrival is not None:  # the third payload: key, length 8, one double
            arr = np.ascontiguousarray(c.arrival, dtype="<f8").reshape(w, 1)
            key = np.frombuffer(_ARRIVAL_KEY, _U8)
            cols += [np.broadcast_to(key, (w, len(key))), arr.view(_U8)]
        mid = encode_block_fields(0, 1, d, 8 * d)
        mid2 = encode_payload2_key(0 if c.second is None else second.shape[1])
        pieces.append((np.frombuffer(mid, _U8), cols[0], np.frombuffer(mid2, _U8), cols[1:]))
    blocks, lengths = [], []
    for i, j, head in _heads(steps, times):
        row = []
        for mid, p1, mid2, rest in pieces:
            n = j - i
            row += [head, np.broadcast_to(mid, (n, len(mid))), p1[i:j]]
            row += [np.broadcast_to(mid2, (n, len(mid2))), *(r[i:j] for r in rest)]
            lengths.append(
                np.full(
                    n,
                    head.shape[1]
                    + len(mid)
                    + p1.shape[1]
                    + len(mid2)
                    + sum(r.shape[1] for r in rest),
                )  # fmt: skip
            )
        blocks.append(np.concatenate(row, axis=1).tobytes() if row else b"")
    # message lengths in message order: instant-major within each run of equal heads
    ends = [np.stack(lengths[b : b + len(pieces)], axis=1).ravel()
            for b in range(0, len(lengths), len(pieces))]  # fmt: skip
    bounds = np.zeros(w * len(columns) + 1, np.int64)
    if ends:
        np.cumsum(np.concatenate(ends), out=bounds[1:])
    return b"".join(blocks), bounds


def log_times(origin: int, times: np.ndarray, repeat: int) -> list[int]:
    """log_time in ns of each instant's `repeat` messages: origin + round(time * 1e9), as
    `McapWriter` stamps one message (rint rounds half to even like ``round``; a double above
    2^53 is an integer)."""
    ns = times * 1e9
    if len(ns) and origin + ns.max() >= 2.0**62:  # beyond int64 arithmetic: Python ints
        return [origin + round(float(x)) for x in ns for _ in range(repeat)]
    return np.repeat(origin + np.rint(ns).astype(np.int64), repeat).tolist()
