"""Issue 34: a late sensor (delays drawn per reading) whose messages carry no ``arrival`` field
-- every reading on time (DESIGN.md "Late measurements": the field is left out for a reading on
time) -- read whole and in blocks of time alike.

The sensors file is written by fusionlog (s3's latency {min = 0, max = 2}) and rewritten with
s3's messages parsed by the official protobuf class and their arrival field discarded. Two
references: the whole log (`state_kind.recorded_arrivals`), and the same file estimated with s3
on time in the filters' model (`--model`, no latency), which the reprocess policy must equal
when every reading arrives at its instant.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_helpers import ok
from long_helpers import OfLargest, arrays_close, summaries, time_block
from mcap.reader import make_reader
from mcap.writer import Writer
from test_long_late_random import ARCHS, BLOCK, RTOL, STEPS, _close, _scenario, _spy

from fusionlog.io.mcap import McapFile
from fusionlog.io.mcap.arrival import iter_arrival_blocks, read_arrivals
from fusionlog.io.mcap.schema import protobuf_classes

LATE = "/sensors/s3"


def _without_arrival(src: Path, dst: Path) -> None:
    """`src` copied record by record, the arrival field of `LATE`'s messages discarded."""
    block_cls, _ = protobuf_classes()  # its schema has no arrival: the field parses unknown
    with open(src, "rb") as f, open(dst, "wb") as g:
        reader = make_reader(f)
        summary = reader.get_summary()
        w = Writer(g)
        w.start(profile=reader.get_header().profile, library="test")
        sids = {s.id: w.register_schema(s.name, s.encoding, s.data)
                for s in summary.schemas.values()}  # fmt: skip
        cids = {
            c.id: w.register_channel(c.topic, c.message_encoding, sids[c.schema_id], c.metadata)
            for c in summary.channels.values()
        }
        for _, channel, m in reader.iter_messages(log_time_order=False):
            data = m.data
            if channel.topic == LATE:
                msg = block_cls.FromString(data)
                msg.DiscardUnknownFields()
                data = msg.SerializeToString()
                assert len(data) == len(m.data) - 10  # key, length, one double
            w.add_message(cids[channel.id], m.log_time, data, m.publish_time, m.sequence)
        for rec in reader.iter_metadata():
            w.add_metadata(rec.name, rec.metadata)
        w.finish()


def _estimate_and_evaluate(sensors: Path, out: Path, block: int | None, mp, *model) -> Path:
    time_block(mp, block)
    out.mkdir()
    ok("estimate", sensors, "-o", out / "estimates.mcap", *model)
    ok("evaluate", sensors, out / "estimates.mcap", "-o", out / "evaluation.rrd",
       "--summary", out / "summary.json")  # fmt: skip
    return out


def _estimates(d: Path, archs) -> dict:
    return McapFile(d / "estimates.mcap").read_all([f"/estimates/{a}" for a in archs])


@pytest.mark.parametrize("late", ["reprocess", "neglect"])
def test_a_late_sensor_without_arrivals_is_on_time_in_blocks_as_whole(tmp_path, late) -> None:
    """Arrivals read in blocks: the messages' times at s3's instants (NaN where it has no
    message); estimates and summary of 12 blocks of 50 as the whole log's; with reprocess, the
    estimates of the filters' model with s3 on time."""
    sc = _scenario(tmp_path, "{min = 0.0, max = 2.0}", True, False, late)
    mp = pytest.MonkeyPatch()
    try:
        time_block(mp, None)
        ok("run", sc, "--out-dir", tmp_path / "sim", "--force")
        src, sensors = tmp_path / "sim" / "sensors.mcap", tmp_path / "on_time.mcap"
        topics = ["/sensors/s1", "/sensors/s2", LATE]
        assert read_arrivals(src, [LATE], 1, STEPS + 1)[LATE] is not None  # drawn, written
        _without_arrival(src, sensors)
        assert read_arrivals(sensors, [LATE], 1, STEPS + 1)[LATE] is None

        f = McapFile(sensors)
        want = np.where(f.topic_steps(LATE), f.times(), np.nan)  # the instants it has messages
        got = np.concatenate(
            [a[:, -1] for *_, a in iter_arrival_blocks(sensors, topics, STEPS + 1, BLOCK)]
        )
        np.testing.assert_array_equal(got, want)

        whole = _estimate_and_evaluate(sensors, tmp_path / "whole", None, mp)
        spy = _spy(mp)
        blocked = _estimate_and_evaluate(sensors, tmp_path / "blocked", BLOCK, mp)
        assert (spy.estimated, spy.evaluated) == (12, 12)
        if late == "reprocess":
            model = tmp_path / "on_time.toml"
            model.write_text(sc.read_text().replace("latency = {min = 0.0, max = 2.0}", ""))
            ref = _estimate_and_evaluate(sensors, tmp_path / "ref", None, mp, "--model", model)
    finally:
        mp.undo()
    a, b = _estimates(whole, ARCHS), _estimates(blocked, ARCHS)
    refs = [a] if late != "reprocess" else [a, _estimates(ref, ARCHS)]
    for t in a:
        for r in refs:
            arrays_close(b[t][0], r[t][0], OfLargest(RTOL), t)
            arrays_close(b[t][1], r[t][1], OfLargest(RTOL), t)
    sa, sb = summaries(whole, blocked)
    _close(sb, sa)
