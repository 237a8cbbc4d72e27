"""`fusionlog inspect`: what a log holds, as lines of text.

For any MCAP: its topics, schemas and message counts; foreign topics with their encoding, rate
and the field paths of their first message with types and values (what a replay file's
`values`, `time` and `covariance` name); for fusionlog's files also the scenario, who wrote it,
runs and instants, and for each sensor its instants, rate and the share of its readings lost.
ROS 1 `.bag` files and ROS 2 bag folders (or their `.db3`) are listed the same way as foreign
MCAP topics. `describe_damaged` reads a damaged MCAP as far as it goes.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap import recover as recover_file
from fusionlog.io.mcap.topics import SENSORS_PREFIX

__all__ = ["describe", "describe_damaged", "sensor_timing"]

_MAX_FIELDS = 60  # per topic: an Imu or Odometry fits, a point cloud's arrays do not matter


def _field_lines(fields: list[tuple[str, str, str]] | str | None) -> Iterator[str]:
    """The field paths of a foreign topic's first message: path, type, first value."""
    pad = " " * 6
    if fields is None:
        return
    if isinstance(fields, str):
        yield f"{pad}(first message not decoded: {fields})"
        return
    for path, kind, value in fields[:_MAX_FIELDS]:
        yield f"{pad}{path:44s} {kind:10s} {value}"
    if len(fields) > _MAX_FIELDS:
        yield f"{pad}... {len(fields) - _MAX_FIELDS} more fields"


def _describe_bag(file: Path) -> Iterator[str]:
    from fusionlog.io.replay import bag_topics  # rosbags: only for bags

    topics = bag_topics(file)
    yield f"{file}"
    yield f"  ROS bag: {len(topics)} topics (field paths of each topic's first message below)"
    for info in topics:
        hz = f", {info['rate']:.4g} Hz" if info["rate"] else ""
        yield f"  {info['topic']:32s} {info['count']:8d} messages  {info['type']}{hz}"
        yield from _field_lines(info.get("error") or info.get("fields"))


def sensor_timing(mf: McapFile, topic: str) -> str:
    """A sensor's instants and rate (its instants per second of the log), and the share of its
    readings lost (NaN) over all runs."""
    at = mf.topic_steps(topic)
    times = mf.times()[at]
    span = float(times[-1] - times[0]) if len(times) > 1 else 0.0
    rate = f"{(len(times) - 1) / span:.4g} Hz" if span > 0 else "one instant"
    share = mf.lost_share(topic)
    return f"measures at {at.sum()} of {len(at)} instants ({rate}), {100 * share:.1f} % lost"


def describe(file: Path) -> Iterator[str]:
    """The lines `fusionlog inspect FILE` prints."""
    from fusionlog.io.replay import source_kind

    if source_kind(Path(file)) == "bag":
        yield from _describe_bag(Path(file))
        return
    if Path(file).is_dir():
        raise FusionlogError(
            f"{file}: is a folder but not a ROS 2 bag (no metadata.yaml); inspect reads MCAP "
            "files, ROS 1 .bag files and ROS 2 bag folders"
        )
    mf = McapFile(file)
    sc = mf.metadata.get("fusionlog.scenario", {})
    prov = mf.metadata.get("fusionlog.provenance", {})
    replay = _is_replay(sc)
    yield f"{file}"
    if sc:
        what = "a replay of recorded data: one run, no seed" if replay else f"seed {sc.get('seed')}"
        yield f"  scenario: {sc.get('name')} ({what})"
    if prov:
        version = prov.get("fusionlog_version", "?")
        yield f"  written by: {prov.get('command', '?')} (fusionlog {version})"
    ours = [t for t in mf.topics if mf.kind_of(t) is not None]
    if ours:
        at = f"instants: {mf.steps()} (k = 0..{mf.steps() - 1})"
        yield f"  one recorded run, {at}{_clock(mf)}" if replay else f"  runs: {mf.runs()}, {at}"
    else:
        yield "  no fusionlog topics (no fusionlog.Block or fusionlog.EstimateBlock streams)"
    foreign, fields = {}, {}
    if len(ours) < len(mf.topics):  # any MCAP's topics: encoding and rate from its indexes
        from fusionlog.io.replay import first_fields, list_topics

        foreign = {t: (enc, rate) for t, _, enc, _, rate in list_topics(file)}
        fields = first_fields(file, [t for t in mf.topics if t not in ours])
    for t in sorted(mf.topics):
        if t in ours:
            kind = f"dim {mf.dim_of(t)}"
        else:
            enc, rate = foreign.get(t, ("?", None))
            hz = f", {rate:.4g} Hz" if rate else ""
            kind = f"not a fusionlog stream ({enc}{hz}; replay it with a replay file)"
        yield f"  {t:32s} {mf.topics[t]:8d} messages  {mf.schema_of(t)}  {kind}"
        if t.startswith(SENSORS_PREFIX) and t in ours:
            yield f"  {'':32s} {sensor_timing(mf, t)}"
        elif t not in ours:
            yield from _field_lines(fields.get(t))
    yield f"  metadata: {', '.join(sorted(mf.metadata)) or 'none'}"


def _is_replay(scenario_record: dict[str, str]) -> bool:
    """Whether a file's ``fusionlog.scenario`` record is a replay file's (one recorded run;
    its seed 0 and M = 1 are no Monte Carlo settings)."""
    from fusionlog.scenario import is_replay_text

    try:
        return is_replay_text(scenario_record.get("toml", ""), "the recorded scenario")
    except FusionlogError:  # a record this version cannot parse: shown as it says
        return False


def _clock(mf: McapFile) -> str:
    """Where a replay's instants are on the recording's clock (its log_time, DESIGN.md)."""
    ns = mf.time_origin_ns()
    try:
        utc = datetime.fromtimestamp(ns // 10**9, tz=UTC).strftime("%Y-%m-%d %H:%M:%S")
    except (OverflowError, OSError, ValueError):
        return f", log_time from {ns} ns"
    return f", log_time from {ns} ns ({utc} UTC)"


def describe_damaged(file: Path) -> Iterator[str]:
    """The lines `fusionlog inspect --recover FILE` prints: what is readable."""
    from fusionlog.io.replay import source_kind

    if source_kind(Path(file)) == "bag":
        raise FusionlogError(
            f"{file}: is a ROS bag; --recover reads damaged MCAP files only (`fusionlog "
            f"inspect {file}` reads a bag, or says why it cannot)"
        )
    info = recover_file(file)
    yield f"{file}: {'damaged: ' + str(info['error']) if info['error'] else 'intact'}"
    for t, c in sorted(info["topics"].items()):
        yield f"  {t:32s} {c:8d} messages readable"
    yield (
        f"  complete runs: {info['complete_runs']}, "
        f"last complete step: {info['last_complete_step']}"
    )
    yield f"  metadata: {', '.join(sorted(info['metadata'])) or 'none'}"
