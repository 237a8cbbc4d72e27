"""The ``fusionlog.layout`` metadata record: the structure of a file, written by its writer.

:class:`~.writer.McapWriter` records what the reader needs to know before reading blocks of
runs — the instants (their times: ``dt`` when they are exactly k·dt, else the list), the total
number of runs, the number of blocks of runs, each topic's ``dim``, and for a topic that has a
message only at some instants (a sensor at its own rate) the steps it has — so that
:class:`~.file.McapFile` learns the structure without decoding the file twice (a long one-run
log's first block of runs is the whole file). The reader checks the record against the file
(topics, message counts, the last block's end, the first messages' steps, times and dims) and
scans the file instead where it does not match or is absent (hand-written logs).

Values are strings (MCAP metadata is a string map); times are JSON numbers, which round-trip
doubles exactly.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from fusionlog.core.timing import regular_times

__all__ = ["LAYOUT_META", "Layout"]

LAYOUT_META = "fusionlog.layout"
_FORMAT = "1"


def _regular(t: np.ndarray, block: int = 1 << 16) -> bool:
    """t_k == k t_1 for every k, a block of instants at a time (no array of the log's length)."""
    return all(
        np.array_equal(np.arange(a, min(a + block, len(t))) * t[1], t[a : a + block])
        for a in range(0, len(t), block)
    )


@dataclass(frozen=True)
class Layout:
    """times (S,) of the instants k = 0..S-1; runs in total; blocks of runs; dims per topic;
    the steps of the topics that do not have a message at every instant."""

    times: np.ndarray
    runs: int
    blocks: int
    dims: dict[str, int]
    sparse: dict[str, list[int]] = field(default_factory=dict)

    @property
    def instants(self) -> int:
        return len(self.times)

    def steps_of(self, topic: str) -> np.ndarray:
        """(S,) bool: the instants at which `topic` has a message (in every block of runs)."""
        mask = np.zeros(self.instants, dtype=bool)
        if topic in self.sparse:
            mask[self.sparse[topic]] = True
        else:
            mask[:] = True
        return mask

    def to_metadata(self) -> dict[str, str]:
        t = self.times
        out = {
            "format": _FORMAT,
            "instants": str(len(t)),
            "runs": str(self.runs),
            "blocks": str(self.blocks),
            "topics": json.dumps(self.dims, sort_keys=True),
        }
        if self.sparse:
            out["sparse"] = json.dumps(self.sparse, sort_keys=True)
        if len(t) >= 2 and _regular(t):
            out["dt"] = repr(float(t[1]))
        else:
            out["times"] = json.dumps([float(x) for x in t])
        return out

    @staticmethod
    def from_metadata(meta: dict[str, str]) -> Layout:
        """Parse a record; ValueError if it is malformed or of another format."""
        try:
            if meta.get("format") != _FORMAT:
                raise ValueError(f"format {meta.get('format')!r}, not {_FORMAT}")
            instants, runs, blocks = (int(meta[k]) for k in ("instants", "runs", "blocks"))
            dims = json.loads(meta["topics"])
            sparse = json.loads(meta.get("sparse", "{}"))
            if "dt" in meta:
                times = regular_times(instants, float(meta["dt"]))
            else:
                times = np.array(json.loads(meta["times"]), dtype=float)
        except (KeyError, TypeError, json.JSONDecodeError) as e:
            raise ValueError(f"{type(e).__name__}: {e}") from None
        if (
            min(instants, runs, blocks) < 0
            or times.shape != (instants,)
            or not isinstance(dims, dict)
            or not all(isinstance(k, str) and type(v) is int for k, v in dims.items())
            or not isinstance(sparse, dict)
            or not all(
                k in dims
                and isinstance(v, list)
                and all(type(i) is int and 0 <= i < instants for i in v)
                and v == sorted(set(v))
                for k, v in sparse.items()
            )
        ):
            raise ValueError("inconsistent fields")
        return Layout(times, runs, blocks, dims, sparse)
