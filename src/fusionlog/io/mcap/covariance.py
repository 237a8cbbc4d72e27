"""The ``covariance`` field of a sensor message (DESIGN.md "MCAP files": a sensor whose R varies
per message carries it, dim x dim, in a one-run log), read block of time by block (issue 34).

A long log's per-message R held whole is 8 dim^2 bytes per instant and sensor; read here through
the column decoder of the readings (`McapFile.topic_tables`, `columns.Table`'s p2/n2), a window
of instants at a time, the whole run being one window (`McapFile.message_covariances_of`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from fusionlog.errors import FusionlogError

from .columns import Table, gather

__all__ = ["covariance_blocks"]


def _check(path: Any, tab: Table, rows: np.ndarray, name: str, d: int) -> None:
    """The messages `rows` of topic `name` carry a covariance of one run, d x d."""
    if (tab.runs[rows] != 1).any() or (tab.n2[rows] != d * d * 8).any():
        raise FusionlogError(
            f"{path}: {name}: a message covariance of {tab.n2[rows[0]] // 8} doubles, not "
            f"{d}x{d} of one run (per-message covariances are for one-run logs)"
        )


def covariance_blocks(
    path: Any,
    tables: Iterator[tuple[int, Table]],
    topic_index: np.ndarray,
    names: Sequence[str],
    dims: Sequence[int],
    instants: int,
    block: int,
    carried: set[str],
) -> Iterator[tuple[int, int, dict[str, np.ndarray]]]:
    """(k0, k1, {topic: (k1 - k0, dim, dim)}) for the consecutive windows of `block` instants of
    a one-run file of `instants` instants whose decoded chunks are `tables` (in time order),
    NaN where a topic's message carries no covariance (or there is none); the names of the
    topics some message of which carries one are added to `carried` as they are met."""

    def fresh(k0: int) -> list[np.ndarray]:
        w = max(0, min(block, instants - k0))
        return [np.full((w, d, d), np.nan) for d in dims]

    k0, cur = 0, fresh(0)
    for _, tab in tables:
        rows = np.flatnonzero(tab.n2 > 0)
        if not len(rows):
            continue
        ti = topic_index[tab.cid[rows]]
        for i in np.unique(ti).tolist():
            _check(path, tab, rows[ti == i], names[i], dims[i])
            carried.add(names[i])
        order = np.argsort(tab.step[rows], kind="stable")
        rows, ti = rows[order], ti[order]
        step = tab.step[rows]
        if step[0] < k0 or step[-1] >= instants:
            bad = int(step[0] if step[0] < k0 else step[-1])
            raise FusionlogError(f"{path}: {names[ti[0]]}: step {bad} out of time order")
        while len(rows):
            j = int(np.searchsorted(step, k0 + block, side="left"))
            for i in np.unique(ti[:j]).tolist():
                sel = np.flatnonzero(ti[:j] == i)
                d = dims[i]
                cur[i][step[sel] - k0] = gather(tab.raw, tab.p2[rows[sel]], d * d).reshape(-1, d, d)
            rows, ti, step = rows[j:], ti[j:], step[j:]
            if len(rows):  # the window is complete: hand it over, start the next
                yield k0, k0 + len(cur[0]), dict(zip(names, cur, strict=True))
                k0 += block
                cur = fresh(k0)
    while k0 < instants:
        yield k0, k0 + len(cur[0]), dict(zip(names, cur, strict=True))
        k0 += block
        cur = fresh(k0)
