"""The ``arrival`` field of a sensor message (DESIGN.md "Late measurements"): when its readings
reached the filters, in seconds -- one value, or one per run when the delays differ.

The field is the Block's third payload (`schema.PAYLOAD_FIELDS`), written after the others and
left out for a reading on time. It is read here through the column decoder of the readings
(`McapFile.topic_tables`, `columns.Table`'s p3/n3: one decoder for the message layout), whole
or block of time by block, with one rule for a message without it (`message_arrivals`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence

import numpy as np

from .columns import Table, gather
from .schema import PAYLOAD_FIELDS, VALUES
from .wire import _LEN, _key, _varint

__all__ = ["arrival_field", "iter_arrival_blocks", "message_arrivals", "read_arrivals"]

_NUMBER = dict(PAYLOAD_FIELDS[VALUES])["arrival"]
_KEY = _varint(_key(_NUMBER, _LEN))


def arrival_field(arrival: np.ndarray | float) -> bytes:
    """The wire bytes of the ``arrival`` field: its key, length and packed doubles."""
    data = np.asarray(arrival, dtype="<f8").ravel().tobytes()
    return _KEY + _varint(len(data)) + data


def message_arrivals(tab: Table) -> tuple[np.ndarray, np.ndarray]:
    """(carried (n,) bool, arrival (n,) s) of a table's messages: the first double of the
    arrival field where a message carries one; where it does not, the reading was on time and
    its arrival is the message's time (the one rule, whole run and blocks alike)."""
    carried = tab.n3 > 0
    arrival = tab.time.copy()
    arrival[carried] = gather(tab.raw, tab.p3[carried], 1)[:, 0]
    return carried, arrival


def _tables(path: str | os.PathLike[str], topics: Sequence[str]):
    from .file import McapFile

    return McapFile(path).topic_tables(list(topics))


def read_arrivals(
    path: str | os.PathLike[str],
    topics: Sequence[str],
    runs: int,
    instants: int,
    on_time: np.ndarray | None = None,
) -> dict[str, np.ndarray | None]:
    """Each topic's arrival times (runs, K+1) in seconds (`message_arrivals`), NaN at instants
    without a message; for a topic none of whose messages carries one (its readings were on
    time) None, or `on_time` (K+1,) at every instant when given."""
    got = {t: np.full((runs, instants), np.nan) for t in topics}
    carried_any = dict.fromkeys(topics, False)
    topic_index, tables = _tables(path, topics)
    try:
        for _, tab in tables:
            ti = topic_index[tab.cid]
            carried, arrival = message_arrivals(tab)
            for i, t in enumerate(topics):
                r = np.flatnonzero(ti == i)
                if not len(r):
                    continue
                carried_any[t] |= bool(carried[r].any())
                one = r[tab.runs[r] == 1]
                got[t][tab.off[one], tab.step[one]] = arrival[one]
                for m in r[tab.runs[r] != 1].tolist():  # a block of runs: one arrival per run
                    off, n, step = int(tab.off[m]), int(tab.runs[m]), int(tab.step[m])
                    a = gather(tab.raw, tab.p3[m : m + 1], int(tab.n3[m]) // 8)[0]
                    got[t][off : off + n, step] = (
                        a if len(a) == n else a[0] if len(a) else arrival[m]
                    )
    finally:
        tables.close()
    if on_time is None:
        return {t: a if carried_any[t] else None for t, a in got.items()}
    times = np.broadcast_to(on_time, (runs, instants))
    return {t: a if carried_any[t] else times for t, a in got.items()}


def iter_arrival_blocks(
    path: str | os.PathLike[str], topics: Sequence[str], instants: int, block: int
) -> Iterator[tuple[int, int, np.ndarray]]:
    """A one-run file's arrival times block of time by block (issue 34): (k0, k1, (k1 - k0,
    len(topics)) s) for consecutive windows of `block` instants, NaN where a topic has no
    message (`message_arrivals` elsewhere: the whole run's values, the whole run never held)."""
    k0 = 0
    cur = np.full((min(block, instants), len(topics)), np.nan)
    topic_index, tables = _tables(path, topics)
    try:
        for _, tab in tables:
            order = np.argsort(tab.step, kind="stable")
            step, ti = tab.step[order], topic_index[tab.cid[order]]
            arrival = message_arrivals(tab)[1][order]
            if len(step) and (step[0] < k0 or step[-1] >= instants):
                bad = int(step[0] if step[0] < k0 else step[-1])
                raise ValueError(f"{path}: {topics[ti[0]]}: step {bad} out of order")
            i = 0
            while i < len(step):
                j = int(np.searchsorted(step, k0 + block, side="left"))
                cur[step[i:j] - k0, ti[i:j]] = arrival[i:j]
                i = j
                if i < len(step):  # the window is complete: hand it over, start the next
                    yield k0, k0 + len(cur), cur
                    k0 += block
                    cur = np.full((min(block, instants - k0), len(topics)), np.nan)
    finally:
        tables.close()
    while k0 < instants:
        yield k0, k0 + len(cur), cur
        k0 += block
        cur = np.full((max(0, min(block, instants - k0)), len(topics)), np.nan)
