"""MCAP layer, one run's messages a window at a time (issue 34: hour-long logs).

Writing: `McapWriter.write_run_steps` encodes a window of instants at once; the file must be,
byte for byte, the one the one-message calls (`write_values` / `write_estimate`, whose bytes
test_mcap_wire checks against the official protobuf classes) write. Reading: `chunk_rows`
finds a chunk's messages through its message indexes; they must be the messages mcap's own
record reader (`breakup_chunk`) finds, also where an index is wrong or incomplete."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import SeekingReader
from mcap.records import ChunkIndex, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from fusionlog.io.mcap import ESTIMATE, VALUES, McapWriter
from fusionlog.io.mcap.chunk_rows import chunk_rows
from fusionlog.io.mcap.run_steps import RunColumn


def _columns(rng: np.random.Generator, w: int) -> list[RunColumn]:
    return [
        RunColumn("/truth", VALUES, rng.normal(size=(w, 2))),
        RunColumn("/sensors/a", VALUES, rng.normal(size=(w, 1)), rng.normal(size=(w, 1, 1))),
        RunColumn("/estimates/A", ESTIMATE, rng.normal(size=(w, 2)), rng.normal(size=(w, 2, 2))),
        RunColumn("/estimates/B", ESTIMATE, rng.normal(size=(w, 3)), rng.normal(size=(w, 3, 3))),
    ]


def _one_by_one(w: McapWriter, k0: int, times: np.ndarray, cols: list[RunColumn]) -> None:
    for i, t in enumerate(times.tolist()):
        for c in cols:
            if c.kind == ESTIMATE:
                w.write_estimate(c.topic, k0 + i, t, 0, c.first[i][None], c.second[i])
            else:
                cov = None if c.second is None else c.second[i][None]
                w.write_values(c.topic, k0 + i, t, 0, c.first[i][None], cov)


def _file(windows, times, cols, at_once: bool, origin: int, chunk_size: int) -> bytes:
    f = io.BytesIO()
    with McapWriter(f, time_origin_ns=origin, chunk_size=chunk_size) as w:
        for a, b in windows:
            part = [c._replace(first=c.first[a - windows[0][0] : b - windows[0][0]],
                               second=None if c.second is None
                               else c.second[a - windows[0][0] : b - windows[0][0]])
                    for c in cols]  # fmt: skip
            t = times[a - windows[0][0] : b - windows[0][0]]
            if at_once:
                w.write_run_steps(a, t, part)
            else:
                _one_by_one(w, a, t, part)
    return f.getvalue()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    k0=st.sampled_from([0, 1, 120, 16_380, 2**21 - 3, 2**28 - 2]),  # the step's varint grows
    w=st.integers(1, 300),
    cuts=st.lists(st.integers(1, 299), max_size=4),
    first_time=st.sampled_from([0.0, -0.0, 0.25, 1e-9]),
    dt=st.sampled_from([0.005, 1.0, 0.0]),
    origin=st.sampled_from([0, 1_700_000_000_123_456_789]),
    seed=st.integers(0, 9),
)
def test_a_window_at_once_is_the_file_written_message_by_message(
    k0, w, cuts, first_time, dt, origin, seed
) -> None:
    """Same bytes whatever the windows: the step and time fields left out at zero (step 0,
    time 0.0 and -0.0), the step's varint of 1-5 bytes, payloads of both kinds, a measurement
    covariance, a time origin, chunks closed in the middle of a window."""
    rng = np.random.default_rng(seed)
    times = first_time + dt * np.arange(w)
    times[0] = first_time  # -0.0 + 0.0 would be 0.0
    cols = _columns(rng, w)
    bounds = sorted({0, w, *(c for c in cuts if c < w)})
    windows = [(k0 + a, k0 + b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    one = _file([(k0, k0 + w)], times, cols, False, origin, 4096)
    assert _file(windows, times, cols, True, origin, 4096) == one


def test_a_step_written_twice_or_a_bad_time_is_refused() -> None:
    w = McapWriter(io.BytesIO())
    w.write_run_steps(0, np.arange(10.0), _columns(np.random.default_rng(0), 10))
    with pytest.raises(ValueError, match="step 5 written twice"):
        w.write_run_steps(5, np.arange(5.0, 15.0), _columns(np.random.default_rng(1), 10))
    truth = [RunColumn("/truth", VALUES, np.zeros((2, 2)))]
    for bad in (np.nan, np.inf, -1.0):
        with pytest.raises(ValueError, match="finite and >= 0"):
            w.write_run_steps(20, np.array([1.0, bad]), truth)
    with pytest.raises(ValueError, match="needs its covariance"):
        w.write_run_steps(30, np.zeros(1), [RunColumn("/estimates/A", ESTIMATE, np.zeros((1, 2)))])
    w.abort()


# ------------------------------------------------------------------------------------------
# reading through the message indexes
# ------------------------------------------------------------------------------------------


def _written(tmp_path, steps: int = 400) -> tuple[bytes, list[ChunkIndex]]:
    rng = np.random.default_rng(5)
    path = tmp_path / "f.mcap"
    with open(path, "wb") as f, McapWriter(f, chunk_size=8192) as w:
        w.write_run_steps(0, 0.1 * np.arange(steps), _columns(rng, steps))
    data = path.read_bytes()
    summary = SeekingReader(io.BytesIO(data)).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 3
    return data, sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def _mcap_messages(data: bytes, ci: ChunkIndex) -> list[Message]:
    f = io.BytesIO(data)
    f.seek(ci.chunk_start_offset)
    chunk = next(iter(StreamReader(f, skip_magic=True, emit_chunks=True).records))
    return [r for r in breakup_chunk(chunk, validate_crc=True) if isinstance(r, Message)]


def _same(rows, msgs: list[Message]) -> None:
    assert rows.cid.tolist() == [m.channel_id for m in msgs]
    got = [bytes(rows.raw[s : s + n]) for s, n in zip(rows.start, rows.length, strict=True)]
    assert got == [bytes(m.data) for m in msgs]


def test_rows_from_the_indexes_are_the_messages_mcap_reads(tmp_path) -> None:
    data, chunks = _written(tmp_path)
    for ci in chunks:  # the first chunk holds the schema and channel records too
        msgs = _mcap_messages(data, ci)
        _same(chunk_rows(io.BytesIO(data), tmp_path, ci), msgs)
        for only in ({1}, {0, 3}):
            _same(chunk_rows(io.BytesIO(data), tmp_path, ci, only),
                  [m for m in msgs if m.channel_id in only])  # fmt: skip


def _indexes(data: bytes, ci: ChunkIndex) -> list[tuple[int, np.ndarray]]:
    """(channel, (count, 2) log_time and offset) of each message index after the chunk."""
    out, pos = [], ci.chunk_start_offset + ci.chunk_length
    end = pos + ci.message_index_length
    while pos < end:
        _, length, cid, rlen = struct.unpack_from("<BQHI", data, pos)
        out.append((cid, np.frombuffer(data, "<u8", rlen // 8, pos + 15).reshape(-1, 2).copy()))
        pos += 9 + length
    return out


def _with_indexes(data: bytes, ci: ChunkIndex, indexes) -> tuple[io.BytesIO, ChunkIndex]:
    """The chunk followed by the given message indexes, and its chunk index."""
    chunk = data[ci.chunk_start_offset : ci.chunk_start_offset + ci.chunk_length]
    recs, offsets = [], {}
    for cid, pairs in indexes:
        body = struct.pack("<HI", cid, pairs.nbytes) + pairs.astype("<u8").tobytes()
        offsets[cid] = ci.chunk_length + sum(map(len, recs))
        recs.append(struct.pack("<BQ", 0x07, len(body)) + body)
    index = b"".join(recs)
    new = ChunkIndex(
        chunk_length=ci.chunk_length, chunk_start_offset=0, compression=ci.compression,
        compressed_size=ci.compressed_size, message_end_time=ci.message_end_time,
        message_index_length=len(index), message_index_offsets=offsets,
        message_start_time=ci.message_start_time, uncompressed_size=ci.uncompressed_size,
    )  # fmt: skip
    return io.BytesIO(chunk + index), new


@pytest.mark.parametrize("damage", ["drop one", "drop a channel", "shift", "other channel"])
def test_a_wrong_index_is_not_trusted(tmp_path, damage) -> None:
    """An index that misses a message, points into a message or names another channel: the
    chunk is read record by record, with every message."""
    data, chunks = _written(tmp_path)
    ci = chunks[1]
    indexes = _indexes(data, ci)
    assert len(indexes) == 4 and all(len(p) > 2 for _, p in indexes)
    if damage == "drop one":
        indexes[2] = (indexes[2][0], np.delete(indexes[2][1], 1, axis=0))
    elif damage == "drop a channel":
        del indexes[1]
    elif damage == "shift":
        indexes[0][1][1, 1] += 3
    else:
        indexes[0] = (indexes[1][0], indexes[0][1])
    f, bad = _with_indexes(data, ci, indexes)
    _same(chunk_rows(f, tmp_path, bad), _mcap_messages(data, ci))


def test_the_files_and_the_scenario_of_a_log_share_one_array_of_instants(tmp_path) -> None:
    """A long one-run log's instants k dt are one read-only array for its scenario's schedule
    and every file written on them, not one each (8 bytes per instant each; issue 34), and
    sensors measuring at every instant cost no array at all."""
    from fusionlog.io.mcap import McapFile
    from fusionlog.scenario import load_scenario
    from fusionlog.stages.run import run_pipeline

    paper = Path(__file__).resolve().parents[1] / "pipeline" / "ajgl2009.toml"
    sc = load_scenario(paper, runs=1, steps=3000)
    run_pipeline(sc, tmp_path, archs=["CKF"], force=True)
    sens, est = McapFile(tmp_path / "sensors.mcap"), McapFile(tmp_path / "estimates.mcap")
    times = sc.schedule.times
    assert sens.times() is times and est.times() is times
    assert not times.flags.writeable
    np.testing.assert_array_equal(times, np.arange(3001) * sc.system.dt)
    assert sc.schedule.measures.shape == (3001, 3) and sc.schedule.measures.all()
    assert sc.schedule.measures.strides == (0, 0)  # a broadcast True
