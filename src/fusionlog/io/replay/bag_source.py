"""Measurements from one topic of a ROS 1 ``.bag`` or a ROS 2 bag folder, through ``rosbags``.

``rosbags`` (pure Python) reads both: a ROS 1 bag carries its message definitions; a ROS 2 bag
(``metadata.yaml`` + ``.db3`` or ``.mcap`` files) may not, and then the standard message types
decode from the ROS 2 Humble type store (``sensor_msgs``, ``nav_msgs``, ``geometry_msgs`` ...).
ROS 1 messages come out with ROS 2 names (``header.stamp.sec``/``nanosec``), so one replay
file's field paths work on both. A source is the ``.bag`` file, the bag folder, or a ``.db3``
file of it (its folder is opened). The default time is the bag's record time (like MCAP's
``log_time``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fusionlog.errors import DamagedFile, FusionlogError

from .extract import Extractor, StreamFields
from .fields import leaf_fields
from .series import Series, fail
from .source import MAX_MCAP_BYTES, open_source
from .topic_listing import one_line

__all__ = ["bag_files", "bag_path", "bag_topics", "is_bag", "read_bag"]


def is_bag(path: Path) -> bool:
    """A ROS 1 bag file, a ROS 2 bag folder, or a ``.db3`` file of one."""
    suffix = path.suffix.lower()
    return suffix in (".bag", ".db3") or (path.is_dir() and (path / "metadata.yaml").is_file())


def bag_path(path: Path) -> Path:
    """What ``rosbags`` opens: the ``.bag`` file, or the ROS 2 bag's folder."""
    return path.parent if path.suffix.lower() == ".db3" else path


def bag_files(source: Path) -> list[Path]:
    """The files ``rosbags`` reads for ``source``: the ``.bag`` file, or every file of the ROS 2
    bag's folder (``metadata.yaml``, the ``.db3`` files); what a command must never write onto."""
    path = bag_path(source)
    if not path.is_dir():
        return [path]
    try:
        return sorted(p for p in path.iterdir() if not p.is_dir())
    except OSError:  # an unreadable folder: opening it reports that
        return [path]


@contextmanager
def _open(source: Path, what: str | None) -> Iterator[Any]:
    from rosbags.highlevel import AnyReader  # rosbags: needed only for bags
    from rosbags.typesys import Stores, get_typestore

    prefix = f"{source}: {what}: " if what else f"{source}: "
    path = bag_path(source)
    if not path.exists():
        raise FusionlogError(f"{prefix}no such file or folder")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise FusionlogError(f"{prefix}a ROS 2 bag folder needs its metadata.yaml")
    # every file rosbags will open is a regular file of bounded size (never a FIFO, a device)
    for f in bag_files(source):
        open_source(f, what, MAX_MCAP_BYTES, "a ROS bag").close()
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # whatever a damaged or foreign file makes rosbags raise
        raise DamagedFile(
            f"{prefix}damaged or not a ROS bag ({type(e).__name__}: {one_line(e)})",
            source,
            recoverable=False,  # `inspect --recover` reads MCAP files only
        ) from None
    try:
        _check_index(reader, source, prefix)
        yield reader
    finally:
        reader.close()


def _index(source: Path) -> str:
    """Where a bag lists its topics: a ROS 2 bag's metadata.yaml, a ROS 1 bag's own records."""
    return "metadata.yaml" if bag_path(source).is_dir() else "the bag's connection records"


def _check_index(reader: Any, source: Path, prefix: str) -> None:
    """Every topic the bag lists has a name and a type (strings) and a message count (an
    integer): a hand-edited metadata.yaml with `name: 7` or `message_count: twelve` made
    rosbags return them as read, and fusionlog fail on them with an internal error."""
    for i, c in enumerate(reader.connections):
        for key, value, want in (
            ("name", c.topic, str),
            ("type", c.msgtype, str),
            ("message_count", c.msgcount, int),
        ):
            if not isinstance(value, want) or isinstance(value, bool):
                kind = "a string" if want is str else "an integer"
                raise DamagedFile(
                    f"{prefix}{_index(source)}: topic entry {i}: {key} {value!r} is not {kind}",
                    source,
                    recoverable=False,
                )


def _unread(source: Path, conns: list[Any]) -> str | None:
    """Why a topic whose index lists messages gave none: the index does not match the storage
    (rosbags reads a ROS 2 topic's messages by its name and type as metadata.yaml gives them)."""
    listed = sum(c.msgcount for c in conns)
    if not listed:
        return None
    return (
        f"{_index(source)} lists {listed} messages of type {conns[0].msgtype}, and the bag's "
        "storage has none of that name and type (does the index match the storage file?)"
    )


def _rate(count: int, first: int | None, last: int | None) -> float | None:
    if count < 2 or first is None or last is None or last <= first:
        return None
    return (count - 1) / ((last - first) * 1e-9)


def _deserialize(reader: Any, source: Path, what: str | None, conn: Any, raw: bytes, k: int):
    try:
        return reader.deserialize(raw, conn.msgtype)
    except Exception as e:  # an unknown type without definitions, or damaged bytes
        prefix = f"{what}: " if what else ""
        raise DamagedFile(
            f"{source}: {prefix}cannot decode message {k} of topic {conn.topic} "
            f"({conn.msgtype}): {type(e).__name__}: {one_line(e)} (a type the bag does not "
            "define and that is not a standard ROS 2 message, or damaged bytes)",
            source,
            recoverable=False,
        ) from None


def _messages(
    reader: Any, source: Path, what: str | None, topic: str, conns: list[Any]
) -> Iterator[tuple[Any, int, bytes]]:
    """The topic's (connection, record time, raw bytes), with whatever a damaged bag makes
    rosbags raise while reading them (a chunk that does not decompress: "Invalid data stream";
    a record header that does not parse) one line naming the bag, the topic and how far it
    read."""
    messages = reader.messages(connections=conns)
    k = 0
    while True:
        try:
            item = next(messages)
        except StopIteration:
            return
        except Exception as e:  # rosbags' errors, and those of its decompressors
            prefix = f"{what}: " if what else ""
            raise DamagedFile(
                f"{source}: {prefix}topic {topic}: damaged ROS bag: cannot read past message {k} "
                f"of the topic ({type(e).__name__}: {one_line(e)})",
                source,
                recoverable=False,
            ) from None
        k += 1
        yield item


def read_bag(source: Path, *, topic: str, fields: StreamFields, what: str) -> Series:
    ex = Extractor(source, what, fields)
    with _open(source, what) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            have = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
            raise fail(source, what, f"no topic {topic} in the bag (topics: {have})")
        col = ex.collector()
        k = 0
        for conn, stamp, raw in _messages(reader, source, what, topic, conns):
            k += 1
            decoded = _deserialize(reader, source, what, conn, raw, k)
            ex.add(col, k, decoded, int(stamp), topic, conn.msgtype)
    if k == 0:
        why = _unread(source, conns)
        raise fail(
            source, what, f"topic {topic}: {why}" if why else f"topic {topic} has no messages"
        )
    return col.finish()


def bag_topics(source: Path) -> list[dict[str, Any]]:
    """What ``inspect`` shows of a bag: per topic (sorted) its type, message count, mean rate
    (record times), and the field paths of its first message with their types and values
    (``fields``), or why it does not decode (``error``)."""
    source = Path(source)
    out = []
    with _open(source, None) as reader:
        by_topic: dict[str, list[Any]] = {}
        for c in reader.connections:
            by_topic.setdefault(c.topic, []).append(c)
        for topic in sorted(by_topic):
            conns = by_topic[topic]
            count = sum(c.msgcount for c in conns)
            info: dict[str, Any] = {"topic": topic, "type": conns[0].msgtype, "count": count}
            first = last = None
            for conn, stamp, raw in _messages(reader, source, None, topic, conns):
                if first is None:
                    try:
                        info["fields"] = leaf_fields(
                            _deserialize(reader, source, None, conn, raw, 1)
                        )
                    except DamagedFile as e:
                        info["error"] = str(e).split(": ", 1)[-1]
                    first = stamp
                last = stamp
            if first is None and (why := _unread(source, conns)):
                info["error"] = why
            info["rate"] = _rate(count, first, last)
            out.append(info)
    return out
