"""Decoding many messages at once into numpy columns.

A chunk's messages are grouped by channel and byte length; each group is checked against the
key and length bytes of its first message (a :class:`Template`) and its fields are read as
numpy columns, so that after mcap has split the chunk into records no Python runs per message
(a fusionlog writer's messages of one topic differ only in their values, except where the
step's varint grows). Messages that fit no template (foreign encodings, long messages) are
decoded one by one with :func:`.wire.decode_fields`; the result is the same (a property test
checks it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .chunk_rows import Rows, message_rows
from .wire import UINT32_MAX, MessageFormat, WireError, decode_fields, payload_span

__all__ = ["BadMessage", "Table", "Template", "decode_rows", "decode_table", "gather"]

_F8 = np.dtype("<f8")

#: Varints of up to this many bytes are decoded in int64 columns (uint32 needs five).
_MAX_VARINT = 5
#: Messages shorter than this are decoded a group at a time (Template), longer ones singly:
#: their bytes dominate, and a template would have to be checked against every payload length.
_SMALL = 4096
#: Payloads of more doubles than this are copied one message at a time (no index arrays).
_GATHER_LOOP = 1024


class BadMessage(Exception):
    """A message that does not decode; ``channel_id`` says where (the reader names the topic)."""

    def __init__(self, channel_id: int, text: str) -> None:
        super().__init__(text)
        self.channel_id = channel_id


@dataclass(frozen=True)
class Template:
    """Where the fields lie in one canonical message, so that every message of the same channel
    and length with the same key and length bytes is decoded at once, as numpy columns.

    Equal keys, lengths and varint continuation bits at the same places make two messages of
    one length parse identically field by field; only the bytes of the values differ. The
    payload bytes are not read here: a message's payloads start at its offset + p1 / p2.
    """

    cols: np.ndarray  # positions read from every message: everything but the payload doubles
    mask: np.ndarray  # per col: 0xFF key/length byte, 0x80 varint value byte, 0 time byte
    expect: np.ndarray  # the template's bytes & mask
    ints: tuple[tuple[int, int] | None, ...]  # step, run_offset, runs, dim: (col, bytes)
    time: int | None  # col of the time's first byte
    p1: tuple[int, int]  # (start, length) of the payloads in the message; (0, 0) if absent
    p2: tuple[int, int]
    p3: tuple[int, int]  # a Block's arrival (`wire.Fields`)

    @staticmethod
    def of(data: bytes, fmt: MessageFormat) -> Template | None:
        """The template of ``data``, or None if it is not canonical (decode one by one)."""
        fast = fmt.fast
        if fast is None:
            return None
        n = len(data)
        m = fast.match(data)
        pos = m.end()  # type: ignore[union-attr]
        payload: list[tuple[int, int]] = []
        for key in (fmt.p1_key, fmt.p2_key, fmt.p3_key):
            if 0 <= pos < n and data[pos] == key:
                a, pos = payload_span(data, pos, n)
                payload.append((a, pos))
            else:
                payload.append((0, 0))
        if pos != n:
            return None
        mask = np.full(n, 0xFF, np.uint8)
        unread = np.zeros(n, bool)  # the payload doubles
        for a, b in payload:
            unread[a:b] = True
        spans = [m.span(g) for g in range(1, 6)]  # type: ignore[union-attr]
        for g, (a, b) in enumerate(spans):
            if a >= 0:
                if g != 1 and b - a > _MAX_VARINT:
                    return None
                mask[a:b] = 0 if g == 1 else 0x80
        cols = np.flatnonzero(~unread)
        where = np.full(n, -1)
        where[cols] = np.arange(len(cols))
        mask = mask[cols]
        ints = tuple(
            None if spans[g][0] < 0 else (int(where[spans[g][0]]), spans[g][1] - spans[g][0])
            for g in (0, 2, 3, 4)
        )
        time = None if spans[1][0] < 0 else int(where[spans[1][0]])
        expect = np.frombuffer(data, np.uint8)[cols] & mask
        spans3 = [(a, b - a) for a, b in payload]
        return Template(cols, mask, expect, ints, time, *spans3)

    def decode(
        self, u8: np.ndarray, starts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The messages at byte offsets ``starts`` of ``u8``: (ok, ints, time) with ints rows
        step, run_offset, runs, dim, p1, n1, p2, n2, p3, n3 (payload offsets in ``u8`` and
        byte lengths); ok is False where a message does not fit the template (decode it singly)."""
        head = u8[starts[:, None] + self.cols]
        ok = ((head & self.mask) == self.expect).all(axis=1)
        ints = np.zeros((10, len(starts)), np.int64)
        for row, spec in enumerate(self.ints):
            if spec is not None:
                c, ln = spec
                v = ints[row]
                for i in range(ln):
                    v |= (head[:, c + i] & 0x7F).astype(np.int64) << (7 * i)
        for row, (a, n) in zip((4, 6, 8), (self.p1, self.p2, self.p3), strict=True):
            ints[row], ints[row + 1] = starts + a, n
        ok &= (ints[:4] <= UINT32_MAX).all(axis=0)  # else decoded singly, which says why
        if self.time is None:
            time = np.zeros(len(starts))
        else:
            c = self.time
            time = np.ascontiguousarray(head[:, c : c + 8]).view("<f8")[:, 0]
        return ok, ints, time


@dataclass
class Table:
    """Messages decoded into columns, in file order.

    The payloads stay in ``raw`` (the messages' bytes joined, then any payload that had to be
    reassembled from pieces): p1/p2/p3 are their byte offsets in it, n1/n2/n3 their byte
    lengths (p3: a Block's arrival, n3 = 0 where a message has none).
    """

    raw: bytes
    cid: np.ndarray
    step: np.ndarray
    off: np.ndarray
    runs: np.ndarray
    dim: np.ndarray
    time: np.ndarray
    p1: np.ndarray
    n1: np.ndarray
    p2: np.ndarray
    n2: np.ndarray
    p3: np.ndarray
    n3: np.ndarray

    def __len__(self) -> int:
        return len(self.cid)


def decode_table(messages: Sequence[Any], formats: dict[int, MessageFormat]) -> Table | None:
    """Decode the messages (mcap ``Message`` records: channel_id, data) whose channel is in
    ``formats`` into columns; None if there is none. Raises BadMessage (`decode_rows`)."""
    return decode_rows(message_rows([m for m in messages if m.channel_id in formats]), formats)


def decode_rows(rows: Rows, formats: dict[int, MessageFormat]) -> Table | None:
    """Decode the messages of ``rows`` whose channel is in ``formats`` into columns; None if
    there is none. Raises BadMessage.

    Messages shorter than _SMALL are grouped by channel and length and each group decoded at
    once against the template of its first message; the rest, and any message that does not
    fit its group's template, one by one. No Python runs per message otherwise.
    """
    keep = np.isin(rows.cid, np.fromiter(formats, np.int64, len(formats)))
    raw, cid, starts, lens = rows.raw, rows.cid[keep], rows.start[keep], rows.length[keep]
    n = len(cid)
    if not n:
        return None
    u8 = np.frombuffer(raw, np.uint8)
    # step, run_offset, runs, dim, p1, n1, p2, n2, p3, n3 (payload offsets in raw, byte lengths)
    cols = np.zeros((10, n), np.int64)
    time = np.zeros(n)
    done = np.zeros(n, bool)
    small = np.flatnonzero(lens < _SMALL)
    if len(small):
        key = cid[small] << 32 | lens[small]
        order = np.argsort(key, kind="stable")
        bounds = np.flatnonzero(np.diff(key[order])) + 1
        for g in np.split(small[order], bounds):
            s0 = int(starts[g[0]])
            tpl = Template.of(raw[s0 : s0 + int(lens[g[0]])], formats[int(cid[g[0]])])
            if tpl is None:
                continue
            ok, ints, t = tpl.decode(u8, starts[g])
            if not ok.all():
                g, ints, t = g[ok], ints[:, ok], t[ok]
            cols[:, g] = ints
            time[g] = t
            done[g] = True
    rest = np.flatnonzero(~done)
    if len(rest):
        raw = _decode_rows(raw, rest, cid, starts, lens, cols, time, formats)
    return Table(raw, cid, *cols[:4], time, *cols[4:])


def _decode_rows(
    raw: bytes,
    rows: np.ndarray,
    cid: np.ndarray,
    starts: np.ndarray,
    lens: np.ndarray,
    cols: np.ndarray,
    time: np.ndarray,
    formats: dict[int, MessageFormat],
) -> bytes:
    """Decode ``rows`` one by one into ``cols``/``time``; return ``raw`` with any payload that
    was split into pieces appended whole (payloads must be contiguous in the table)."""
    mv = memoryview(raw)
    extra: list[bytes] = []
    end = len(raw)
    for i in rows.tolist():
        s, c = int(starts[i]), int(cid[i])
        try:
            fields = decode_fields(mv[s : s + int(lens[i])], formats[c])
        except WireError as e:
            raise BadMessage(c, str(e)) from e
        step, t, off, runs, dim, *payloads = fields
        if max(step, off, runs, dim) > UINT32_MAX:
            raise BadMessage(
                c,
                f"step {step}, run_offset {off}, runs {runs}, dim {dim}: each must fit in 32 bits",
            )
        cols[:4, i] = step, off, runs, dim
        time[i] = t
        for j, q in zip((4, 6, 8), payloads, strict=True):
            if len(q) == 1:
                cols[j, i], cols[j + 1, i] = s + q[0][0], q[0][1] - q[0][0]
            elif q:
                piece = b"".join(mv[s + a : s + b] for a, b in q)
                extra.append(piece)
                cols[j, i], cols[j + 1, i] = end, len(piece)
                end += len(piece)
    mv.release()
    return b"".join([raw, *extra]) if extra else raw


def gather(raw: bytes, starts: np.ndarray, nvals: int) -> np.ndarray:
    """(len(starts), nvals) little-endian doubles read from ``raw`` at byte offsets ``starts``.

    The offsets are rarely multiples of 8; numpy reads unaligned arrays, so ``raw`` is viewed
    as doubles once per residue mod 8 and whole doubles are gathered (an index per double,
    not per byte).
    """
    count = len(starts)
    out = np.empty((count, nvals), _F8)
    if not count or not nvals:
        return out
    if nvals > _GATHER_LOOP:
        for i, s in enumerate(starts.tolist()):
            out[i] = np.frombuffer(raw, _F8, nvals, s)
        return out
    res = starts & 7
    cols = np.arange(nvals)
    for j in np.flatnonzero(np.bincount(res, minlength=8)).tolist():
        view = np.frombuffer(raw, _F8, (len(raw) - j) // 8, j)
        sel = res == j
        at = (starts[sel] - j) >> 3
        out[sel] = view[at[:, None] + cols]
    return out
