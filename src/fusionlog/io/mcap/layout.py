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

The lists are written for at most `LISTED` instants (issue 34). A longer log whose times are
not k·dt or that has a sparse topic gets the record without them (its counts and dims, and
``unlisted``: the lists left out), and the reader learns them from a scan of the file, as for
a file without a record: the record was one metadata string that the foxglove SDK copies
whole at close (~130 bytes of RSS per instant for an irregular 10^6-row import, the writer's
times 8 more, all until the file closes), and the reader holds its text at open too. The scan
costs ~0.8 s of CPU at open for 10^6 instants of three topics (1.4 s against 0.6 s through the
record, `benchmarks/README.md` issue 34); a regular log's record (``dt``, every topic dense)
stays bounded and is written as before, and files written with the lists still open through
them.

In memory (issue 34) a sparse topic's steps are a `StepMask`, one bit per instant, and the
record's JSON lists are written and parsed a stretch of `_STRETCH` numbers at a time with numpy,
the text the same as `json.dumps` of the lists: a Python list of the steps (a 36-byte int each,
and a set of them to check the order) took ~600 bytes per instant at its peak when a long
sparse log was opened.
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from fusionlog.core.timing import regular_times

__all__ = ["LAYOUT_META", "LISTED", "Layout", "StepMask"]

LAYOUT_META = "fusionlog.layout"
_FORMAT = "1"
#: The most instants whose times (and sparse topics' steps) the record lists: ~2.3 MB of text
#: at most; past it the reader scans (module docstring).
LISTED = 1 << 16
#: Numbers of a JSON list written or parsed at once (their text and arrays: some 10 kB).
_STRETCH = 1 << 12


class StepMask:
    """The instants 0..S-1 at which a topic has a message: one bit each (`np.packbits` order),
    and their count. `mask[k0:k1]` is the (k1 - k0,) bool mask of a window (a block of time
    unpacks only its own bits)."""

    __slots__ = ("bits", "count", "instants")

    def __init__(self, bits: np.ndarray, instants: int, count: int) -> None:
        self.bits, self.instants, self.count = bits, instants, count

    @staticmethod
    def of_steps(parts: Iterator[np.ndarray] | list[np.ndarray], instants: int) -> StepMask:
        """The mask of the steps given as increasing arrays, stretch by stretch; ValueError
        where a step is out of 0..S-1 or not above the one before."""
        bits = np.zeros((instants + 7) // 8, dtype=np.uint8)
        last, count = -1, 0
        for steps in parts:
            if not len(steps):
                continue
            if steps[0] <= last or steps[-1] >= instants or (np.diff(steps) <= 0).any():
                raise ValueError("steps not increasing within 0..S-1")
            np.bitwise_or.at(bits, steps >> 3, (128 >> (steps & 7)).astype(np.uint8))
            last, count = int(steps[-1]), count + len(steps)
        return StepMask(bits, instants, count)

    @staticmethod
    def of_mask(mask: np.ndarray) -> StepMask:
        """The (S,) bool `mask` as bits."""
        return StepMask(np.packbits(mask), len(mask), int(np.count_nonzero(mask)))

    def __getitem__(self, window: slice) -> np.ndarray:
        k0, k1, step = window.indices(self.instants)
        if step != 1 or k1 <= k0:
            return self.full()[window]
        a = k0 // 8
        return np.unpackbits(self.bits[a : (k1 + 7) // 8], count=k1 - 8 * a)[k0 - 8 * a :] > 0

    def full(self) -> np.ndarray:
        """(S,) bool."""
        return np.unpackbits(self.bits, count=self.instants) > 0

    def stretches(self) -> Iterator[np.ndarray]:
        """The steps, in increasing arrays of a stretch of instants each."""
        for a in range(0, self.instants, 8 * _STRETCH):
            yield np.flatnonzero(self[a : a + 8 * _STRETCH]) + a


def _json_list(parts: Iterator[list]) -> str:
    """`json.dumps` of the list of the items of `parts` (lists of ints or finite floats:
    their text is `repr`'s), written a part at a time."""
    return "[" + ", ".join(t for p in parts if p for t in [", ".join(map(repr, p))]) + "]"


_NUMBERS = re.compile(r"[0-9eE+\-.,\s]*")


def _numbers(text: str, start: int, dtype: type) -> tuple[Iterator[np.ndarray], int]:
    """The numbers of the JSON list of ints or floats that starts at text[start] (``[``), as
    arrays of up to ~`_STRETCH` numbers, and the index after its ``]``; ValueError where it is
    not such a list (then `json` says what is wrong)."""
    if text[start] != "[":
        raise ValueError("not a list")
    end = text.index("]", start)
    cuts = [start + 1]
    while cuts[-1] < end:  # stretches cut after a comma
        at = text.find(",", min(cuts[-1] + 24 * _STRETCH, end), end)
        cuts.append(end if at < 0 else at + 1)

    def parts() -> Iterator[np.ndarray]:
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            piece = text[a : b if b == end else b - 1]  # without the comma it was cut after
            if not _NUMBERS.fullmatch(piece):
                raise ValueError("not a list of numbers")
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                got = np.fromstring(piece, dtype=dtype, sep=",") if piece.strip() else None
            if got is None:
                if b != end or a != start + 1:
                    raise ValueError("an empty item")
                continue
            if len(got) != piece.count(",") + 1:
                raise ValueError("not a list of numbers")
            yield got

    return parts(), end + 1


def _sparse_of(text: str, instants: int) -> dict[str, StepMask]:
    """The ``sparse`` record ({topic: [steps]}) as `StepMask`s, parsed a stretch at a time."""
    dec = json.JSONDecoder()
    out: dict[str, StepMask] = {}
    i = _skip(text, 0)
    if text[i] != "{":
        raise ValueError("not an object")
    i = _skip(text, i + 1)
    while text[i] != "}":
        key, i = dec.raw_decode(text, i)
        i = _skip(text, i)
        if not isinstance(key, str) or text[i] != ":":
            raise ValueError("not an object of lists")
        parts, i = _numbers(text, _skip(text, i + 1), np.int64)
        out[key] = StepMask.of_steps(parts, instants)
        i = _skip(text, i)
        if text[i] == ",":
            i = _skip(text, i + 1)
        elif text[i] != "}":
            raise ValueError("not an object of lists")
    if text[i + 1 :].strip():
        raise ValueError("text after the object")
    return out


def _skip(text: str, i: int) -> int:
    while text[i] in " \t\r\n":
        i += 1
    return i


def _times_of(text: str, instants: int) -> np.ndarray:
    """The ``times`` record (a JSON list of doubles) as an array, parsed a stretch at a time;
    `json` where it is not plain numbers (NaN, or malformed: its error)."""
    try:
        parts, end = _numbers(text, _skip(text, 0), float)
        out, at = np.empty(instants), 0
        for p in parts:
            if at + len(p) > instants:
                raise ValueError("too many")
            out[at : at + len(p)], at = p, at + len(p)
        if at == instants and not text[end:].strip():
            return out
    except (ValueError, IndexError):
        pass
    return np.array(json.loads(text), dtype=float)


def _regular(t: np.ndarray, block: int = 1 << 16) -> bool:
    """t_k == k t_1 for every k, a block of instants at a time (no array of the log's length)."""
    return all(
        np.array_equal(np.arange(a, min(a + block, len(t))) * t[1], t[a : a + block])
        for a in range(0, len(t), block)
    )


@dataclass(frozen=True)
class Layout:
    """times (S,) of the instants k = 0..S-1; runs in total; blocks of runs; dims per topic;
    the steps of the topics that do not have a message at every instant. A writer's layout
    past `LISTED` instants may leave the lists out: `times` None, `count` the instants, and
    `unlisted` names what the record does not list ("times", "sparse")."""

    times: np.ndarray | None
    runs: int
    blocks: int
    dims: dict[str, int]
    sparse: dict[str, StepMask] = field(default_factory=dict)
    count: int = -1  # the instants, where `times` is None
    unlisted: tuple[str, ...] = ()

    @property
    def instants(self) -> int:
        return self.count if self.times is None else len(self.times)

    def steps_of(self, topic: str) -> np.ndarray:
        """(S,) bool: the instants at which `topic` has a message (in every block of runs)."""
        if topic in self.sparse:
            return self.sparse[topic].full()
        return np.ones(self.instants, dtype=bool)

    def count_of(self, topic: str) -> int:
        """The number of instants at which `topic` has a message."""
        return self.sparse[topic].count if topic in self.sparse else self.instants

    def to_metadata(self) -> dict[str, str]:
        t = self.times
        out = {
            "format": _FORMAT,
            "instants": str(self.instants),
            "runs": str(self.runs),
            "blocks": str(self.blocks),
            "topics": json.dumps(self.dims, sort_keys=True),
        }
        if self.unlisted:  # the reader scans the file for them
            out["unlisted"] = " ".join(self.unlisted)
            return out
        if self.sparse:
            out["sparse"] = "{" + ", ".join(
                f"{json.dumps(k)}: {_json_list(s.tolist() for s in self.sparse[k].stretches())}"
                for k in sorted(self.sparse)
            ) + "}"  # fmt: skip
        if len(t) >= 2 and _regular(t):
            out["dt"] = repr(float(t[1]))
        elif np.isfinite(t).all():
            out["times"] = _json_list(
                t[a : a + _STRETCH].astype(float).tolist() for a in range(0, len(t), _STRETCH)
            )
        else:
            out["times"] = json.dumps([float(x) for x in t])
        return out

    @staticmethod
    def from_metadata(meta: dict[str, str]) -> Layout:
        """Parse a record; ValueError if it is malformed or of another format, or does not
        list the times and steps (``unlisted``: the reader scans the file)."""
        try:
            if meta.get("format") != _FORMAT:
                raise ValueError(f"format {meta.get('format')!r}, not {_FORMAT}")
            if "unlisted" in meta:
                raise ValueError(f"lists left out: {meta['unlisted']}")
            instants, runs, blocks = (int(meta[k]) for k in ("instants", "runs", "blocks"))
            dims = json.loads(meta["topics"])
            if min(instants, runs, blocks) < 0:
                raise ValueError("a negative count")
            sparse = _sparse_of(meta.get("sparse", "{}"), instants)
            if "dt" in meta:
                times = regular_times(instants, float(meta["dt"]))
            else:
                times = _times_of(meta["times"], instants)
        except (KeyError, TypeError, IndexError, json.JSONDecodeError) as e:
            raise ValueError(f"{type(e).__name__}: {e}") from None
        if (
            times.shape != (instants,)
            or not isinstance(dims, dict)
            or not all(isinstance(k, str) and type(v) is int for k, v in dims.items())
            or not all(k in dims for k in sparse)
        ):
            raise ValueError("inconsistent fields")
        return Layout(times, runs, blocks, dims, sparse)
