"""Reading measurements out of recorded files for replay (DESIGN.md, "Replay files").

``read_series`` reads one stream - an MCAP topic of any encoding (ROS 2 CDR, protobuf, JSON), a
topic of a ROS 1 ``.bag`` or a ROS 2 bag folder, or a text table of any extension - into a
:class:`Series`: measurement times (ns, sorted), values, and optionally the per-message
covariance blocks. One reader per format behind this one function (``source_kind`` decides
which). ``list_topics`` and ``bag_topics`` describe a log's topics for ``inspect``;
``to_enu`` turns geodetic fixes into local metres.

Modules: :mod:`.fields` (field paths into decoded messages, times), :mod:`.extract` (values,
time, covariance of one message), :mod:`.decoders` (the MCAP decoder factories),
:mod:`.topic_listing` (opening an MCAP, its topics and rates), :mod:`.mcap_source`,
:mod:`.bag_source`, :mod:`.text_source`, :mod:`.geodetic`, :mod:`.series` (the Series and the
checks every source shares).

Every problem is a one-line :class:`fusionlog.errors.FusionlogError` (``ValidationError`` for
the content, ``DamagedFile`` for a damaged MCAP) starting ``<source>: <what>: ``, or a counted
note in ``Series.notes``: messages out of time order are sorted (stable), messages with NaN/inf
values (or time) skipped, non-finite covariance entries returned as read. All-zero or
non-positive-definite covariance blocks are returned as read: the caller decides.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from fusionlog.errors import FusionlogError

from .bag_source import bag_files, bag_topics, is_bag, read_bag
from .extract import StreamFields
from .fields import leaf_fields
from .geodetic import to_enu
from .mcap_source import first_fields, read_mcap
from .series import Series, fail
from .text_source import TUM_COLUMNS, read_text
from .topic_listing import list_topics

__all__ = [
    "Series",
    "TUM_COLUMNS",
    "bag_topics",
    "first_fields",
    "leaf_fields",
    "list_topics",
    "read_series",
    "read_streams",
    "source_files",
    "source_kind",
    "to_enu",
]


def source_kind(source: Path) -> str:
    """ "mcap", "bag" (ROS 1 ``.bag``, ROS 2 bag folder or its ``.db3``) or "text" (any other
    file: a table)."""
    if source.suffix.lower() == ".mcap" and not source.is_dir():
        return "mcap"
    if is_bag(source):
        return "bag"
    return "text"


def source_files(source: Path) -> list[Path]:
    """The files a reader of ``source`` opens (a ROS 2 bag: every file of its folder)."""
    source = Path(source)
    return bag_files(source) if source_kind(source) == "bag" else [source]


def read_series(
    source: Path,
    *,
    topic: str | None,
    values: Sequence[str],
    time: str | None = None,
    time_unit: str = "s",
    covariance: str | None = None,
    covariance_index: Sequence[int] | None = None,
    delimiter: str | None = None,
    columns: Sequence[str] | None = None,
    format: str | None = None,  # noqa: A002 (the replay file's key)
    what: str = "sensors[0]",
) -> Series:
    """One recorded stream of ``source``: an MCAP or bag ``topic``, or a text table.

    ``values``: field paths into the decoded message (``pose.pose.position.x``, ``[i]`` for
    array elements) or column names (as written in the header, surrounding spaces ignored, or
    as named by ``columns``). ``time``: a field holding a ROS time (``sec``/``nanosec``) or a
    number in ``time_unit`` (s|ms|us|ns), or a column; default the MCAP ``log_time`` or bag
    record time, or the column ``time`` (``timestamp`` in the TUM format). ``covariance``: a
    field holding a flat row-major square matrix; ``covariance_index``: its rows/columns that
    belong to ``values`` (all of it when omitted and its size is ``len(values)``);
    ``cov[n] = M[np.ix_(idx, idx)]``. ``delimiter``, ``columns``, ``format`` ("tum"): text
    tables only (:mod:`.text_source`). ``what`` names the stream in messages (``sensors[0]``,
    ``truth``).
    """
    source = Path(source)
    fields = StreamFields(values, time, time_unit, covariance, covariance_index)
    fields.check(source, what)
    kind = source_kind(source)
    if kind in ("mcap", "bag"):
        if not isinstance(topic, str) or not topic:
            raise fail(
                source, what, f"an {'MCAP' if kind == 'mcap' else 'ROS bag'} source needs a topic"
            )
        for key, v in (("delimiter", delimiter), ("columns", columns), ("format", format)):
            if v is not None:
                raise fail(source, what, f"{key} is for text tables, not for {source.name}")
        reader = read_mcap if kind == "mcap" else read_bag
        return reader(source, topic=topic, fields=fields, what=what)
    if topic is not None:
        raise fail(
            source, what, f"topic {topic!r} given for a text table (topics are MCAP's and bags')"
        )
    if covariance is not None:
        raise fail(
            source,
            what,
            "covariance fields are read from messages (MCAP, bags) only; for a table give R",
        )
    if format not in (None, "tum"):
        raise fail(source, what, f"format {format!r} is not known (known: tum)")
    return read_text(source, values=list(values), time=time, time_unit=time_unit, what=what,
                     delimiter=delimiter, columns=columns, fmt=format)  # fmt: skip


def _table_key(source: Path, args: dict, what: str) -> tuple | None:
    """The (file, delimiter, columns) a stream shares with the others of its table, where
    `.text_fast` may read it; None for a stream read on its own (not a plain table, or keys
    whose error `read_series` gives)."""
    try:
        StreamFields(args["values"], args.get("time"), args.get("time_unit", "s")).check(
            source, what
        )
    except FusionlogError:
        return None
    if source_kind(source) != "text" or args.get("format") is not None:
        return None
    if any(args.get(k) is not None for k in ("topic", "covariance", "covariance_index")):
        return None
    columns = args.get("columns")
    return (source, args.get("delimiter"), None if columns is None else tuple(columns))


def _request(source: Path, args: dict, what: str):
    from .text_fast import TextRequest

    return TextRequest(what, tuple(args["values"]), args.get("time"), args.get("time_unit", "s"))


def read_streams(streams: Sequence[tuple[Path, dict, str]]) -> list[Series]:
    """``read_series(source, **args, what=what)`` of each stream in order, with the same
    results and the same first error, but each text table read once for all the streams that
    name it (`.text_fast`; where it does not read a stream, `read_series` does)."""
    streams = [(Path(s), a, w) for s, a, w in streams]
    keys = [_table_key(*st) for st in streams]
    tables: dict[tuple, dict[int, Series | None]] = {}
    out = []
    for i, (source, args, what) in enumerate(streams):
        key, series = keys[i], None
        if key is not None:
            if key not in tables:  # read when its first stream comes: errors stay in order
                from .text_fast import read_table_streams  # pyarrow: only for a table

                group = [j for j, k in enumerate(keys) if k == key]
                requests = [_request(*streams[j]) for j in group]
                read = read_table_streams(source, key[1], key[2], requests)
                tables[key] = dict(zip(group, read, strict=True))
            series = tables[key].pop(i)  # dropped once taken: no table outlives its streams
        out.append(series if series is not None else read_series(source, **args, what=what))
    return out
