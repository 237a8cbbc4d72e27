"""McapFile: reading fusionlog's MCAP files (and one-run logs in the same layout) block by
block of runs.

The file format is the contract in DESIGN.md ("MCAP files"); the writing order the reader
relies on is in :mod:`.writer`. Opening checks the container and its CRCs (:mod:`.chunks`) and
finds which topics are fusionlog streams (:mod:`.wire`, by the fields of their schemas). The
structure (times of the instants, total runs, dims) comes from the writer's
``fusionlog.layout`` record, checked against the file (:mod:`.layout`), or else from a scan
of the first block of runs. Blocks of runs are read chunk by chunk: each chunk is decoded into
columns (:mod:`.columns`) and copied into output blocks (:mod:`.blocks`), so no Python runs
per message here.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fusionlog.errors import FusionlogError
from fusionlog.inputs import check_input

from .blocks import Assembly, Cursor, Window
from .chunk_rows import Rows, chunk_rows, first_message
from .chunks import Container, linear_batches, open_container, open_error, read_chunk
from .columns import BadMessage, Table, decode_rows, decode_table
from .layout import LAYOUT_META, Layout, StepMask
from .scan import ScanSteps
from .schema import ESTIMATE_SCHEMA, SENSOR_SCHEMA, VALUES
from .wire import MessageFormat, format_of_schema_record

__all__ = ["McapFile"]


@dataclass
class _TopicInfo:
    channel_ids: list[int]
    schema: str
    message_encoding: str
    format: MessageFormat | None
    count: int = 0


@dataclass
class _Structure:
    """Times of the instants, dims per topic and total runs."""

    times: np.ndarray
    dims: dict[str, int]
    runs: int
    sparse: dict[str, StepMask] = field(default_factory=dict)  # see Layout.sparse

    def steps_of(self, topic: str) -> np.ndarray:
        """(K+1,) bool: the instants at which `topic` has a message."""
        return Layout(self.times, self.runs, 0, self.dims, self.sparse).steps_of(topic)


#: The layout record's fields that grow with the log (`Layout.to_metadata`): dropped from
#: `McapFile.metadata` once the structure is read from them (issue 34).
_LISTS = ("times", "sparse")


class McapFile:
    """A fusionlog MCAP file opened for reading; opening validates the container, its CRCs and
    the schemas.

    Holds no open file handle: every read opens its own, so instances are cheap and need no
    closing.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._structure: _Structure | None = None
        self._origin: int | None = None  # time_origin_ns, read once
        #: topics whose messages carry no covariance (`covariance_blocks`: not read again)
        self._no_covariances: set[str] = set()
        check_input(self.path)  # a FIFO or a device would block or never end
        try:
            with open(self.path, "rb") as f:
                c = open_container(f, self.path)
        except OSError as e:
            raise open_error(self.path, e) from e
        self._container = c
        self.metadata: dict[str, dict[str, str]] = c.metadata
        self.library = c.library
        self._topics = self._find_topics(c)
        self._formats: dict[int, MessageFormat] = {
            cid: info.format
            for info in self._topics.values()
            if info.format is not None
            for cid in info.channel_ids
        }
        self.topics: dict[str, int] = {t: info.count for t, info in self._topics.items()}

    def _find_topics(self, c: Container) -> dict[str, _TopicInfo]:
        topics: dict[str, _TopicInfo] = {}
        formats: dict[int, MessageFormat | None] = {}
        for cid in sorted(c.channels):
            ch = c.channels[cid]
            schema = c.schemas.get(ch.schema_id)
            fmt = None
            if schema is not None and ch.message_encoding == "protobuf":
                if schema.id not in formats:
                    formats[schema.id] = format_of_schema_record(
                        schema.encoding, schema.name, schema.data
                    )
                fmt = formats[schema.id]
                if fmt is None and schema.name in (SENSOR_SCHEMA, ESTIMATE_SCHEMA):
                    raise FusionlogError(
                        f"{self.path}: topic {ch.topic} claims schema {schema.name} but its "
                        "descriptor lacks the fusionlog fields"
                    )
            name = schema.name if schema is not None else ""
            info = topics.get(ch.topic)
            if info is None:
                info = _TopicInfo([], name, ch.message_encoding, fmt)
                topics[ch.topic] = info
            elif (info.format and info.format.kind) != (fmt and fmt.kind):
                raise FusionlogError(
                    f"{self.path}: topic {ch.topic} has channels with different schemas "
                    f"({info.schema}, {name})"
                )
            info.channel_ids.append(cid)
            info.count += c.counts.get(cid, 0)
        return topics

    # -- decoded chunks ------------------------------------------------------------------------

    def _tables(self, cids: set[int], start: int = 0) -> Iterator[tuple[int, Table]]:
        """(ordinal, table) of every chunk from the ``start``-th that has messages of ``cids``.

        Ordinals count chunks (batches of messages in a file without index), so a block of runs
        can be read again from where it started without keeping its bytes.
        """
        formats = {c: self._formats[c] for c in cids}
        with open(self.path, "rb") as f:
            if self._container.linear:
                for bi, batch in enumerate(linear_batches(f, self.path, cids)):
                    tab = self._table(batch, formats) if bi >= start else None
                    if tab is not None:
                        yield bi, tab
                return
            # Few of the file's messages wanted (evaluate reads /truth only, which every chunk
            # interleaves with the sensors): take them through the chunks' message indexes.
            wanted = sum(i.count for i in self._topics.values() if set(i.channel_ids) & cids)
            total = sum(i.count for i in self._topics.values())
            sparse = 2 * wanted <= total
            chunks = self._container.chunks
            for ci in range(start, len(chunks)):
                index, ids = chunks[ci]
                if ids is not None and not ids & cids:
                    continue
                only = cids & ids if sparse and ids is not None else None
                tab = self._table(chunk_rows(f, self.path, index, only), formats)
                if tab is not None:
                    yield ci, tab

    def _table(self, msgs: list[Any] | Rows, formats: dict[int, MessageFormat]) -> Table | None:
        try:
            if isinstance(msgs, Rows):
                return decode_rows(msgs, formats)
            return decode_table(msgs, formats)
        except BadMessage as e:
            topic = self._topic_of()[e.channel_id]
            raise FusionlogError(f"{self.path}: bad protobuf message on {topic}: {e}") from e

    # -- structure -----------------------------------------------------------------------------

    def _topic_of(self) -> dict[int, str]:
        return {cid: t for t, i in self._topics.items() for cid in i.channel_ids}

    def _get_structure(self) -> _Structure:
        """Steps, times and dims from the layout record or the first block of runs; total runs
        from the last block."""
        if self._structure is None:
            cids = set(self._formats)
            self._structure = self._recorded_structure(cids) or self._scan_structure(cids)
        return self._structure

    def _recorded_structure(self, cids: set[int]) -> _Structure | None:
        """The structure the writer recorded (``fusionlog.layout``), checked against the file's
        topics and message counts, its last block and its first messages, so that a long
        one-run log is not decoded twice (once to learn its steps, once to read it). None:
        absent or not matching; scan instead."""
        meta = self.metadata.get(LAYOUT_META)
        if meta is None:
            return None
        try:
            lay = Layout.from_metadata(meta)
        except ValueError:
            return None
        finally:  # the lists' text (~35 bytes per instant) read once: parsed, or refused
            self.metadata[LAYOUT_META] = {k: v for k, v in meta.items() if k not in _LISTS}
        ours = {t: i for t, i in self._topics.items() if i.format is not None}
        if set(lay.dims) != set(ours) or any(
            i.count != lay.count_of(t) * lay.blocks for t, i in ours.items()
        ):
            return None
        if lay.runs != self._last_run_end(cids):
            return None
        # The first table's messages of the first block: steps, times and dims as recorded,
        # and every step of every topic if the block ends in this table. (The block reader
        # checks each message's step against 0..K and its dim, and that no step is missing.)
        topic_of = self._topic_of()
        for _, tab in self._tables(cids):
            first = np.flatnonzero(tab.off == 0)
            if not len(first):
                return None
            steps = tab.step[first]
            if steps.max() >= lay.instants or (tab.time[first] != lay.times[steps]).any():
                return None
            for i in first.tolist():
                if tab.dim[i] != lay.dims[topic_of[int(tab.cid[i])]]:
                    return None
            if len(first) < len(tab):  # the first block ends here: all its steps are in
                cid = tab.cid[first]
                for c in np.unique(cid).tolist():
                    have = np.unique(steps[cid == c])
                    if not np.array_equal(have, np.flatnonzero(lay.steps_of(topic_of[c]))):
                        return None
            break
        return _Structure(lay.times, dict(lay.dims), lay.runs, dict(lay.sparse))

    def _scan_structure(self, cids: set[int]) -> _Structure:
        """Steps, times, dims and the sparse topics' steps from the first block of runs,
        reduced chunk by chunk to each step's first time, each topic's first dim and its steps'
        bits (`ScanSteps`), since a one-run log's first block is the whole file: memory grows
        with the steps only (their times, 8 bytes each, and a bit per topic)."""
        topic_of = self._topic_of()
        names = sorted(set(topic_of.values()))
        key_of = np.zeros(max(topic_of, default=0) + 1, np.int64)
        key_of[list(topic_of)] = [names.index(t) for t in topic_of.values()]
        scan = ScanSteps()
        dims: dict[str, int] = {}
        first: int | None = None
        for _, tab in self._tables(cids):
            if first is None:
                first = int(tab.off[0])
            other = np.flatnonzero(tab.off != first)
            j = int(other[0]) if len(other) else len(tab)
            scan.add(tab.step[:j], tab.time[:j], key_of[tab.cid[:j]])
            _, at = np.unique(tab.cid[:j], return_index=True)
            for i in sorted(at.tolist()):
                dims.setdefault(topic_of[int(tab.cid[i])], int(tab.dim[i]))
            if j < len(tab):
                break
        times, masks = scan.result(self.path)
        if first not in (None, 0):
            raise FusionlogError(f"{self.path}: the first block of runs starts at run {first}")
        sparse = {names[k]: m for k, m in masks.items() if m.count != len(times)}
        return _Structure(times, dims, self._last_run_end(cids), sparse)

    def _last_run_end(self, cids: set[int]) -> int:
        """End of the last block of runs: the blocks are in order, so read only the last chunk."""
        chunks, linear = self._container.chunks, self._container.linear
        candidates = [ci for ci, (_, ids) in enumerate(chunks) if ids is None or ids & cids]
        start = candidates[-1] if candidates and not linear else 0
        end = 0
        for _, tab in self._tables(cids, start):
            end = max(end, int((tab.off + tab.runs).max()))
        return end

    def schema_of(self, topic: str) -> str:
        """Schema name of ``topic`` (e.g. ``fusionlog.Block``)."""
        return self._info(topic).schema

    def kind_of(self, topic: str) -> str | None:
        """``"values"``, ``"estimate"``, or None for a topic fusionlog cannot read."""
        fmt = self._info(topic).format
        return fmt.kind if fmt is not None else None

    def dim_of(self, topic: str) -> int:
        """``dim`` of a topic's messages (state size n for estimates)."""
        self._readable(topic)
        dims = self._get_structure().dims
        if topic not in dims:
            raise FusionlogError(f"{self.path}: topic {topic} has no message in the first block")
        return dims[topic]

    def steps(self) -> int:
        """Number of time steps K + 1 (distinct steps of the first block of runs)."""
        return len(self._get_structure().times)

    def topic_steps(self, topic: str) -> np.ndarray:
        """(K+1,) bool: the instants at which `topic` has a message (a sensor measuring at its
        own rate has some only; its readings are NaN at the others)."""
        self._info(topic)
        return self._get_structure().steps_of(topic)

    def message_covariances(self, topic: str) -> np.ndarray | None:
        """(K+1, dim, dim): the per-message measurement covariance of a values topic of a
        one-run log (the Block's optional ``covariance``), NaN at instants without one; None
        when no message of the topic carries one."""
        return self.message_covariances_of([topic])[topic]

    def message_covariances_of(self, topics: Sequence[str]) -> dict[str, np.ndarray | None]:
        """`message_covariances` of several topics from one pass over the file (one window of
        `covariance_blocks`). A file of several runs has none (the block reader refuses a
        message that carries one in such a file)."""
        out: dict[str, np.ndarray | None] = dict.fromkeys(topics)
        carried: set[str] = set()
        for _, _, got in self.covariance_blocks(topics, self.steps(), carried):
            out.update((t, got[t]) for t in carried)
        return out

    def covariance_blocks(
        self, topics: Sequence[str], block: int, carried: set[str]
    ) -> Iterator[tuple[int, int, dict[str, np.ndarray]]]:
        """`covariance.covariance_blocks` of values topics of a one-run log (none of more
        runs), `carried` given the topics that carry one; the others are not read again."""
        from .covariance import covariance_blocks

        infos = {t: self._readable(t) for t in dict.fromkeys(topics)}
        for t, info in infos.items():
            if info.format.kind != VALUES:  # type: ignore[union-attr]
                raise ValueError(f"{t} is not a values topic")
        names = [t for t in infos if t not in self._no_covariances]
        if not names or self.runs() != 1:
            return
        topic_index, tables = self.topic_tables(names)
        try:
            yield from covariance_blocks(
                self.path, tables, topic_index, names, [self.dim_of(t) for t in names],
                self.steps(), max(1, block), carried,
            )  # fmt: skip
        finally:
            tables.close()
        self._no_covariances.update(t for t in names if t not in carried)

    def lost_share(self, topic: str, block_runs: int = 1 << 14) -> float:
        """Share of a values topic's readings that are NaN (lost: a dropout) over the runs and
        the instants at which the topic has a message."""
        at = self.topic_steps(topic)
        lost = total = 0
        for _, _, data in self.iter_run_blocks([topic], block_runs):
            v = data[topic][:, at]
            lost += int(np.isnan(v).any(axis=-1).sum())
            total += v.shape[0] * v.shape[1]
        return lost / total if total else 0.0

    def runs(self) -> int:
        """Total number of Monte Carlo runs in the file."""
        return self._get_structure().runs

    def times(self) -> np.ndarray:
        """(K + 1,) time in seconds of each step (first message of that step in the file), read
        only: one array however often asked for (a copy costs 8 bytes an instant)."""
        t = self._get_structure().times
        t.flags.writeable = False
        return t

    def share_times(self, times: np.ndarray) -> None:
        """Hold `times` for this file's where equal (one array for a log's two files, issue 34)."""
        s = self._get_structure()
        if np.array_equal(s.times, times):
            s.times = times

    def time_origin_ns(self) -> int:
        """The clock of the file's messages: log_time - round(time * 1e9) of its first fusionlog
        message, i.e. the absolute time of instant 0 (0 for a simulation, a replay's recorded
        time of its first instant). Files written from this one take it as their writer's
        `time_origin_ns`: the same log_time at each instant (DESIGN.md "MCAP files": a replay's
        outputs keep its clock). A log_time before its `time` (hand-written) gives 0."""
        if self._origin is None:
            cids, first = set(self._formats), []
            with open(self.path, "rb") as f:
                if self._container.linear:
                    first = next(iter(linear_batches(f, self.path, cids)), [])
                else:
                    ci = next((c for c, ids in self._container.chunks if ids is None or ids & cids),
                              None)  # fmt: skip
                    one = None if ci is None else first_message(f, self.path, ci, cids)
                    first = [one] if one else [] if ci is None else read_chunk(f, self.path, ci)
            first = [m for m in first if m.channel_id in cids][:1]
            tab = self._table(first, self._formats) if first else None
            origin = 0 if tab is None else first[0].log_time - round(float(tab.time[0]) * 1e9)
            self._origin = origin if 0 <= origin < 2**63 else 0
        return self._origin

    def _info(self, topic: str) -> _TopicInfo:
        info = self._topics.get(topic)
        if info is None:
            have = ", ".join(sorted(self._topics)) or "none"
            raise FusionlogError(f"{self.path}: no topic {topic} (topics: {have})")
        return info

    def _readable(self, topic: str) -> _TopicInfo:
        info = self._info(topic)
        if info.format is None:
            raise FusionlogError(
                f"{self.path}: topic {topic} has schema {info.schema or '(none)'} "
                f"({info.message_encoding}), not a fusionlog Block or EstimateBlock"
            )
        return info

    # -- blocks of runs ------------------------------------------------------------------------

    def iter_run_blocks(
        self, topics: Sequence[str], block_runs: int
    ) -> Iterator[tuple[int, int, dict[str, Any]]]:
        """Yield (run_offset, runs, {topic: data}) for consecutive blocks of ``block_runs`` runs.

        A values topic gives an array (runs, K+1, dim); an estimate topic gives (mean, cov) with
        mean (runs, K+1, n) and cov (K+1, n, n) if every message of this block had one shared
        covariance (the same across the file's blocks), else (runs, K+1, n, n).

        Memory stays around two output blocks plus two chunks, whatever the file's block size:
        the file is read sequentially, and a file block larger than the output window is read
        again for each window (where it starts is remembered, its bytes are not).
        """
        if block_runs < 1:
            raise ValueError("block_runs must be >= 1")
        names = list(dict.fromkeys(topics))
        if not names:
            raise ValueError("no topics to read")
        infos = [self._readable(t) for t in names]
        st = self._get_structure()
        total = st.runs
        tidx = {cid: ti for ti, info in enumerate(infos) for cid in info.channel_ids}
        cids = set(tidx)
        topic_index = np.zeros(max(cids) + 1, np.int64)
        topic_index[list(tidx)] = list(tidx.values())
        kinds = [i.format.kind for i in infos]  # type: ignore[union-attr]
        dims = [self.dim_of(t) for t in names]
        masks = [st.steps_of(t) for t in names]
        asm = Assembly(self.path, names, dims, kinds, topic_index, masks, total, block_runs)
        tables = self._tables(cids)
        try:
            cur: Cursor = (next(tables, None), 0)
            expected = 0
            while cur[0] is not None:
                (ci, tab), row = cur
                o, r = int(tab.off[row]), int(tab.runs[row])
                topic = names[topic_index[tab.cid[row]]]
                if o != expected:
                    raise asm.bad(
                        f"{topic}: block of runs at run {o} where run {expected} was expected"
                    )
                if r < 1 or o + r > total:
                    raise asm.bad(f"{topic}: block at run {o} has {r} runs of {total}")
                b = asm.add_blocks(o + r)
                start = (ci, row)
                cur = asm.read_block(tables, cur, Window(o, r, o, b, True))
                yield from asm.finished(b)
                # A file block wider than the window: read it again for each further window.
                while b < o + r:
                    a, b = b, asm.add_blocks(o + r)
                    again = self._tables(cids, start[0])
                    try:
                        asm.read_block(again, (next(again), start[1]), Window(o, r, a, b, False))
                    finally:
                        again.close()
                    yield from asm.finished(b)
                expected = o + r
        finally:
            tables.close()
        if expected != total:
            raise asm.bad(f"the requested topics cover runs 0..{expected} of {total}")

    def iter_time_blocks(
        self, topics: Sequence[str], steps: int
    ) -> Iterator[tuple[int, int, dict[str, Any]]]:
        """A one-run file's (k0, k1, {topic: data}) for consecutive windows of `steps` instants
        (`time_blocks`): the shapes of `iter_run_blocks` with k1 - k0 instants in place of K+1."""
        from .time_blocks import time_blocks

        names = list(dict.fromkeys(topics))
        infos = [self._readable(t) for t in names]
        st = self._get_structure()
        if st.runs != 1:
            raise ValueError("blocks of time are read from a one-run log")
        kinds = [i.format.kind for i in infos]  # type: ignore[union-attr]
        dims = [self.dim_of(t) for t in names]
        masks = [st.sparse.get(t) for t in names]  # each block unpacks its own bits
        topic_index, tables = self.topic_tables(names)
        try:
            yield from time_blocks(
                self.path, tables, names, dims, kinds, topic_index, masks, max(1, steps),
                len(st.times),
            )  # fmt: skip
        finally:
            tables.close()

    def topic_tables(self, topics: Sequence[str]) -> tuple[np.ndarray, Iterator[tuple[int, Table]]]:
        """Each channel id's index in `topics`, and their messages as columns chunk by chunk."""
        tidx = {cid: ti for ti, t in enumerate(topics) for cid in self._readable(t).channel_ids}
        topic_index = np.full(max(tidx) + 1, -1, np.int64)
        topic_index[list(tidx)] = list(tidx.values())
        return topic_index, self._tables(set(tidx))

    def read_all(self, topics: Sequence[str]) -> dict[str, Any]:
        """All runs of ``topics`` at once (small files, tests); same shapes as iter_run_blocks."""
        total = self.runs()
        for _, _, data in self.iter_run_blocks(topics, max(total, 1)):
            return data
        return {}
