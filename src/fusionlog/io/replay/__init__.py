"""Reading measurements out of recorded files for replay (DESIGN.md, "Replay files").

``read_series`` reads one stream - an MCAP topic of any encoding (ROS 2 CDR, protobuf, JSON) or a
CSV file - into a :class:`Series`: measurement times (ns, sorted), values, and optionally the
per-message covariance blocks. ``list_topics`` describes any MCAP's topics for ``inspect``.

Modules: :mod:`.fields` (field paths into decoded messages, times), :mod:`.decoders` (the
decoder factories), :mod:`.topics` (opening an MCAP, its topics and rates), :mod:`.mcap_source`,
:mod:`.csv_source`, :mod:`.series` (the Series and the checks every source shares).

Every problem is a one-line :class:`fusionlog.errors.FusionlogError` (``ValidationError`` for
the content, ``DamagedFile`` for a damaged MCAP) starting ``<source>: <what>: ``, or a counted
note in ``Series.notes``: messages out of time order are sorted (stable), messages with NaN/inf
values (or time) skipped, non-finite covariance entries returned as read. All-zero or
non-positive-definite covariance blocks are returned as read: the caller decides.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from .csv_source import read_csv
from .fields import TIME_UNITS
from .mcap_source import read_mcap
from .series import Series, fail
from .topics import list_topics

__all__ = ["Series", "list_topics", "read_series"]


def _check_args(
    source: Path,
    what: str,
    values: Sequence[str],
    time: str | None,
    time_unit: str,
    covariance: str | None,
    covariance_index: Sequence[int] | None,
) -> None:
    if isinstance(values, str) or not values:
        raise fail(source, what, "values must be a non-empty list of field paths or columns")
    for v in values:
        if not isinstance(v, str) or not v.strip():
            raise fail(source, what, f"values: {v!r} is not a field path or column name")
    if time is not None and (not isinstance(time, str) or not time.strip()):
        raise fail(source, what, f"time: {time!r} is not a field path or column name")
    if time_unit not in TIME_UNITS:
        raise fail(source, what, f"time_unit {time_unit!r} is not one of {', '.join(TIME_UNITS)}")
    if covariance is not None and (not isinstance(covariance, str) or not covariance.strip()):
        raise fail(source, what, f"covariance: {covariance!r} is not a field path")
    if covariance_index is None:
        return
    if covariance is None:
        raise fail(source, what, "covariance_index is given without covariance")
    idx = list(covariance_index)
    if not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in idx):
        raise fail(source, what, f"covariance_index {idx} must be non-negative integers")
    if len(idx) != len(values):
        raise fail(
            source,
            what,
            f"covariance_index has {len(idx)} entries but values has {len(values)}: one row/column "
            "of the covariance per value",
        )
    if len(set(idx)) != len(idx):
        raise fail(source, what, f"covariance_index {idx} repeats a row/column")


def read_series(
    source: Path,
    *,
    topic: str | None,
    values: Sequence[str],
    time: str | None = None,
    time_unit: str = "s",
    covariance: str | None = None,
    covariance_index: Sequence[int] | None = None,
    what: str = "sensors[0]",
) -> Series:
    """One recorded stream of ``source`` (``.mcap`` with ``topic``, or ``.csv`` without).

    ``values``: field paths into the decoded message (``pose.pose.position.x``, ``[i]`` for
    array elements) or CSV column names as written in the header (surrounding spaces ignored).
    ``time``: a field holding a ROS time (``sec``/``nanosec``) or a number in ``time_unit``
    (s|ms|us|ns), or a CSV column; default the MCAP ``log_time``, or the CSV column ``time`` in
    ``time_unit``. ``covariance``: a field holding a flat row-major square matrix;
    ``covariance_index``: its rows/columns that belong to ``values`` (all of it when omitted
    and its size is ``len(values)``); ``cov[n] = M[np.ix_(idx, idx)]``. ``what`` names the
    stream in messages (``sensors[0]``, ``truth``).
    """
    source = Path(source)
    _check_args(source, what, values, time, time_unit, covariance, covariance_index)
    kind = source.suffix.lower()
    if kind == ".mcap":
        if not isinstance(topic, str) or not topic:
            raise fail(source, what, "an MCAP source needs a topic")
        kw = {"time_unit": time_unit, "covariance": covariance, "what": what}
        return read_mcap(source, topic=topic, values=list(values), time=time,
                         covariance_index=covariance_index, **kw)  # fmt: skip
    if kind == ".csv":
        if topic is not None:
            raise fail(source, what, f"topic {topic!r} given for a CSV source (topics are MCAP's)")
        if covariance is not None:
            raise fail(
                source,
                what,
                "covariance fields are read from MCAP messages only; for a CSV source give R",
            )
        return read_csv(source, values=list(values), time=time, time_unit=time_unit, what=what)
    raise fail(
        source,
        what,
        f"unsupported source type {source.suffix or '(no extension)'!r}: expected .mcap or .csv",
    )
