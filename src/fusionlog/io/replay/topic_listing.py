"""Opening any MCAP with the plain ``mcap`` reader, and what its topics are.

``list_topics`` is what ``fusionlog inspect`` shows for a file that is not fusionlog's: topic,
schema, message encoding, message count and mean rate. Channels, schemas and counts come from the
summary section; the rates from the chunks' message indexes (log times only, nothing
decompressed), or, in a file without them, from one pass over the messages' log times.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.decoder import DecoderFactory
from mcap.reader import McapReader, make_reader
from mcap.records import Channel, MessageIndex, Schema
from mcap.stream_reader import StreamReader

from fusionlog.errors import DamagedFile

from .decoders import decoder_factories
from .source import MAX_MCAP_BYTES, open_source

__all__ = ["TopicInfo", "catalog", "damaged", "list_topics", "one_line", "open_mcap"]


def one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def damaged(path: Path, e: BaseException, what: str | None = None, where: str = "") -> DamagedFile:
    """``<path>: [<what>: ]damaged ...``; ``where`` names the message that could not be read."""
    prefix = f"{path}: {what}: " if what else f"{path}: "
    name = type(e).__name__
    if name.islower():  # struct.error, zlib.error: say which
        name = f"{type(e).__module__}.{name}"
    exc = f"{name}: {one_line(e)}"
    if where:
        return DamagedFile(
            f"{prefix}cannot read or decode {where}: {exc} (a damaged file, or messages that do "
            "not match their schema)",
            path,
        )
    return DamagedFile(f"{prefix}damaged or not an MCAP file ({exc})", path)


@contextmanager
def open_mcap(
    path: Path, what: str | None = None, factories: list[DecoderFactory] | None = None
) -> Iterator[tuple[McapReader, BinaryIO]]:
    """A seeking reader with ``factories`` (default: :func:`.decoders.decoder_factories`),
    chunk CRCs checked."""
    f = open_source(path, what, MAX_MCAP_BYTES, "an MCAP")  # closed by the with below
    with f:
        try:
            factories = decoder_factories() if factories is None else factories
            reader = make_reader(f, validate_crcs=True, decoder_factories=factories)
        except Exception as e:  # whatever a damaged file makes the library raise
            raise damaged(path, e, what) from None
        yield reader, f


@dataclass
class TopicInfo:
    topic: str
    channels: list[tuple[Channel, Schema | None]] = field(default_factory=list)
    count: int | None = 0
    first: int | None = None  # log times (ns), when asked for
    last: int | None = None

    @property
    def schema_names(self) -> str:
        names = dict.fromkeys(s.name if s is not None else "" for _, s in self.channels)
        return ", ".join(names)

    @property
    def encodings(self) -> str:
        return ", ".join(dict.fromkeys(c.message_encoding for c, _ in self.channels))


def _scan(reader: McapReader, topics: dict[str, TopicInfo]) -> None:
    """One pass over every message (not decoded): channels, counts and log-time range."""
    seen: set[int] = set()
    for info in topics.values():
        info.count, info.first, info.last = 0, None, None
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        info = topics.setdefault(channel.topic, TopicInfo(channel.topic))
        if channel.id not in seen:
            seen.add(channel.id)
            if all(c.id != channel.id for c, _ in info.channels):
                info.channels.append((channel, schema))
        info.count = (info.count or 0) + 1
        t = message.log_time
        info.first = t if info.first is None else min(info.first, t)
        info.last = t if info.last is None else max(info.last, t)


def _index_times(reader: McapReader, f: BinaryIO) -> dict[int, tuple[int, int, int]] | None:
    """(count, first, last log time) per channel id from the chunks' message indexes, or None
    when the file has no chunk index or a chunk without message indexes."""
    summary = reader.get_summary()
    if summary is None or not summary.chunk_indexes:
        return None
    out: dict[int, tuple[int, int, int]] = {}
    for ci in summary.chunk_indexes:
        if ci.message_index_length == 0 and ci.chunk_length > 0:
            return None
        for cid, offset in ci.message_index_offsets.items():
            f.seek(offset, io.SEEK_SET)
            rec = next(StreamReader(f, skip_magic=True).records)
            if not isinstance(rec, MessageIndex) or rec.channel_id != cid:
                raise ValueError(f"no message index at offset {offset}")
            if not rec.records:
                continue
            times = [t for t, _ in rec.records]
            n, lo, hi = out.get(cid, (0, min(times), max(times)))
            out[cid] = (n + len(times), min(lo, *times), max(hi, *times))
    return out


def catalog(reader: McapReader, f: BinaryIO, *, times: bool = False) -> dict[str, TopicInfo]:
    """Topic -> channels (with their schemas), message count, and with ``times`` the first and
    last log time. Library exceptions propagate (the caller turns them into ``damaged``)."""
    summary = reader.get_summary()
    topics: dict[str, TopicInfo] = {}
    if summary is None:
        _scan(reader, topics)
        return topics
    counts: dict[int, int] | None = (
        summary.statistics.channel_message_counts if summary.statistics is not None else None
    )
    for cid in sorted(summary.channels):
        ch = summary.channels[cid]
        info = topics.setdefault(ch.topic, TopicInfo(ch.topic))
        info.channels.append((ch, summary.schemas.get(ch.schema_id)))
    if counts is not None:
        for info in topics.values():
            info.count = sum(counts.get(c.id, 0) for c, _ in info.channels)
    if not times and counts is not None:
        return topics
    idx = _index_times(reader, f)
    if idx is None:
        _scan(reader, topics)
        return topics
    for info in topics.values():
        per = [idx[c.id] for c, _ in info.channels if c.id in idx]
        info.count = sum(p[0] for p in per)
        info.first = min((p[1] for p in per), default=None)
        info.last = max((p[2] for p in per), default=None)
    return topics


def _rate(info: TopicInfo) -> float | None:
    if not info.count or info.count < 2 or info.first is None or info.last is None:
        return None
    span = info.last - info.first
    return (info.count - 1) / (span * 1e-9) if span > 0 else None


def list_topics(path: str | Path) -> list[tuple[str, str, str, int, float | None]]:
    """(topic, schema name, message encoding, message count, mean rate in Hz or None) for every
    topic of any MCAP file, sorted by topic. Several channels on one topic are summed, their
    schema names and encodings joined by ", "."""
    path = Path(path)
    with open_mcap(path) as (reader, f):
        try:
            topics = catalog(reader, f, times=True)
        except Exception as e:  # a damaged file, whatever the library raises
            raise damaged(path, e) from None
    return [
        (t, info.schema_names, info.encodings, int(info.count or 0), _rate(info))
        for t, info in sorted(topics.items())
    ]
